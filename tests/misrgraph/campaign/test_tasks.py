"""The campaign's input task with matched observations: a scenario matched part-way (a run killed
between two passes' matching) is completed on the rerun, to the same measurements."""

from __future__ import annotations

import numpy as np
import pytest

from misrgraph.campaign import tasks
from misrgraph.io.imagery import has_matched, read_matched
from misrgraph.runs.match import run_match


@pytest.mark.slow
def test_a_scenario_matched_part_way_is_completed_on_the_rerun(tmp_path) -> None:
    scfg = {
        "scenario": "path",
        "truth": "model",
        "seed": 5,
        "n_passes": 2,
        "n_tie_points": 15,
        "n_check_points": 2,
        "duration_s": 300.0,
        "start_lat_deg": 52.0,
        "imagery": True,
    }
    d = tmp_path / "path_037"
    out, skipped, s = tasks._simulate(d, scfg, match=True)
    assert out == d and not skipped and s["matched"]["tie"] > 0 and s["matched"]["gcp"] > 0
    files = sorted((d / "passes").glob("*.h5"))
    assert len(files) == 2 and all(has_matched(f) for f in files)
    whole = {f.name: tasks._sha(f) for f in files}
    # found done: nothing is redone
    assert tasks._simulate(d, scfg, match=True)[1] is True
    assert {f.name: tasks._sha(f) for f in files} == whole
    # the same scenario simulated again and matched in its first pass only, as a killed run leaves it
    e = tmp_path / "again"
    tasks._simulate(e, scfg, match=False)
    first, second = sorted((e / "passes").glob("*.h5"))
    run_match(e, pass_file=first)
    assert has_matched(first) and not has_matched(second)
    out, skipped, s2 = tasks._simulate(e, scfg, match=True)
    assert not skipped and has_matched(second)
    # deterministic: the completed scenario holds the measurements the uninterrupted one does (the
    # files' digests differ: the match summary records the seconds it took)
    assert s2["matched"] == s["matched"]
    for f in files:
        a, b = read_matched(f), read_matched(e / "passes" / f.name)
        for name in ("landmark", "camera", "band", "line", "sample", "sigma_px"):
            np.testing.assert_array_equal(getattr(a.observations, name), getattr(b.observations, name), err_msg=name)
        np.testing.assert_array_equal(a.landmarks.id, b.landmarks.id)
