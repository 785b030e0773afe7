"""``bench cgm`` at reduced size: a camera step between two short calibration windows, the store
picking version 1 before it and version 2 after it, and the stale version worse than the new one
for a step far larger than either calibration's sigma."""

from __future__ import annotations

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from misrgraph.commands.cli import app


def test_step_arcsec_moves_the_pointing_by_the_step():
    """The delta change of ``step_arcsec`` moves the camera's pointing by the step (linear in it:
    half the angle, half the step)."""
    from misrgraph.bench.cgm import step_arcsec
    from misrgraph.estimate.calibrate import pointing_error_px
    from misrgraph.model.constants import ARCSEC, CAMERAS
    from misrgraph.model.nominal import nominal_camera_model

    m = nominal_camera_model()
    for cam in ("Df", "An", "Da"):
        c = CAMERAS.index(cam)
        for px in (0.1, 2.0):
            moved = m.copy()
            moved.add_correction("delta", c, None, step_arcsec(cam, px) * ARCSEC)
            assert pointing_error_px(moved, m, c) == pytest.approx(px, rel=1e-3)


@pytest.mark.slow
def test_bench_cgm_new_version_against_the_stale_one(tmp_path):
    r = CliRunner().invoke(
        app,
        ["bench", "cgm", "--passes", "3", "--window-days", "3", "--gcps", "20", "--step-px", "2", "--seed", "1",
         "--workdir", str(tmp_path), "--json"],
    )  # fmt: skip
    assert r.exit_code == 0, r.output
    res = json.loads(r.stdout)
    assert res["versions_used"] == {"before": ["v001"], "after": ["v002"]}
    assert res["provenance"]["bench"] == "cgm"
    # the passes after the step fly the stepped camera: their truth against window 1's
    from misrgraph.io.camera import read_camera_file
    from misrgraph.io.truth import read_pass_truth
    from misrgraph.model.constants import ARCSEC, CAMERAS

    # the passes after the step are paired with those before it: the same attitude error draws
    before = sorted((tmp_path / "before" / "passes").glob("*.h5"))
    after = sorted((tmp_path / "after" / "passes").glob("*.h5"))
    for fb, fa in zip(before, after):
        kb, ka = (np.asarray(read_pass_truth(f).attitude_error.knots) for f in (fb, fa))
        assert np.array_equal(kb, ka) and np.abs(kb).max() > 0
    assert set(res["new_minus_before"]) == {"checkpoint_rms_m", "coregistration_px", "camera_nees"}
    base = read_camera_file(tmp_path / "window1" / "camera_truth.h5")
    c = CAMERAS.index("Da")
    for stretch, moved in (("before", 0.0), ("after", res["step"]["arcsec"])):
        for f in sorted((tmp_path / stretch / "passes").glob("*.h5")):
            assert (read_pass_truth(f).camera_model.delta[c] - base.delta[c]) / ARCSEC == pytest.approx(moved, abs=1e-9)
    # a 2 px step, several times either calibration's sigma: the stale version co-registers Da
    # worse on every pass, and its camera NEES is larger
    sig = res["calibration_sigma_px"]
    assert 2.0 > 3 * max(sig["version1"], sig["version2"]), sig
    per = res["per_pass"]
    stale = np.array([p["coregistration_px"] for p in per["after_stale"]])
    new = np.array([p["coregistration_px"] for p in per["after_new"]])
    assert np.all(stale > new), (stale, new)
    assert res["stale_minus_new"]["camera_nees"]["mean"] > 0
    bad = CliRunner().invoke(app, ["bench", "cgm", "--step-camera", "Dz"])
    assert bad.exit_code == 2 and "step_camera" in bad.output
