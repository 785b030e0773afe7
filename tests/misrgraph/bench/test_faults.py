"""SIGKILL trials (reduced: 3 per command; ``misrgraph bench kill`` runs 20): every file is the old
one or a complete new one, no pass is counted twice, a rerun completes."""

from __future__ import annotations

import pytest

from misrgraph.bench.faults import KILL_COMMANDS, run_kill_trials
from misrgraph.errors import InputError


@pytest.mark.slow
def test_kill_trials_leave_old_or_complete_new_files(tmp_path):
    res = run_kill_trials(KILL_COMMANDS, trials=3, seed=1, workdir=tmp_path)
    assert set(res["commands"]) == set(KILL_COMMANDS)
    for name, r in res["commands"].items():
        assert r["old"] + r["new"] + r["none"] + r["half_written"] + r["lost"] + r["counted_twice"] == 3, (name, r)
        assert r["half_written"] == r["lost"] == r["counted_twice"] == r["rerun_failed"] == 0, (name, r)
    assert res["failures"] == 0
    # the study sees both sides of the commit over all commands (kills land before and after it)
    assert sum(r["old"] + r["none"] for r in res["commands"].values()) > 0


def test_kill_study_judges_a_half_written_file_as_a_failure(tmp_path):
    """The judge is not vacuous: a truncated output is half-written, a missing one lost."""
    from misrgraph.bench.faults import _Adjust

    t = _Adjust(tmp_path, {})
    t.out.write_bytes(b"\x00" * 2000)
    assert t.judge(None, 0) == "half_written"
    t.out.unlink()
    assert t.judge("0" * 64, 0) == "lost"


def test_kill_study_rejects_unknown_commands():
    with pytest.raises(InputError, match="commands"):
        run_kill_trials(("frobnicate",), trials=1)
