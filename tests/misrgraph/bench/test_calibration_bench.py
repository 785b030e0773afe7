"""``bench calibration`` at reduced size: the month's LM step by both orderings and the cameras'
covariance by both factorisations of the reduced system give the same numbers (timings are
reported, never asserted)."""

from __future__ import annotations

import pytest

from misrgraph.bench.calibration import run_bench_calibration
from misrgraph.errors import InputError


def test_both_methods_give_the_same_step_and_covariance(tmp_path) -> None:
    r = run_bench_calibration("reduced", seed=200, workdir=tmp_path, repeat=1)
    assert r["passes"] > 10 and r["cameras"] == 9 and r["landmarks"] <= 24
    # the same linear system solved two ways: they agree to round-off of its conditioning
    assert r["step"]["relative_difference"] < 1e-8, r["step"]
    assert r["camera_covariance"]["relative_difference"] < 1e-6, r["camera_covariance"]
    for part in ("step", "camera_covariance"):
        assert r[part]["former_s"] > 0 and r[part]["current_s"] > 0
        assert r[part]["ratio"] == pytest.approx(r[part]["former_s"] / r[part]["current_s"])


def test_bad_size_and_repeat_are_clear_errors(tmp_path) -> None:
    with pytest.raises(InputError, match="size"):
        run_bench_calibration("huge", workdir=tmp_path)
    with pytest.raises(InputError, match="repeat"):
        run_bench_calibration("reduced", workdir=tmp_path, repeat=0)
