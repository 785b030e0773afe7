"""``misrgraph bench roi``'s refusals (the bench itself simulates standard passes: ``bench``, not the suite)."""

from __future__ import annotations

import pytest
from typer.testing import CliRunner

from misrgraph.commands.cli import app


@pytest.mark.parametrize(
    "args, field",
    [
        (["--passes", "3"], "--passes"),
        (["--blocks", "0"], "--blocks"),
        (["--first-block", "175", "--blocks", "10"], "--first-block"),
        (["--first-block", "0"], "--first-block"),
    ],
)
def test_bench_roi_refuses_bad_input(args, field, tmp_path) -> None:
    r = CliRunner().invoke(app, ["bench", "roi", "--workdir", str(tmp_path / "w"), *args])
    assert r.exit_code == 2 and field in r.output, r.output
    assert not (tmp_path / "w").exists()  # refused before anything is simulated
