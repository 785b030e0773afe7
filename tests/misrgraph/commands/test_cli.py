from __future__ import annotations

import json
import subprocess
import sys

import pytest
from typer.testing import CliRunner

from misrgraph.commands.cli import app
from misrgraph.model.constants import CAMERAS

runner = CliRunner()


def test_sensitivity_json_shape():
    res = runner.invoke(app, ["sensitivity", "--arcsec", "10", "--pixel", "0", "--band", "red", "--json"])
    assert res.exit_code == 0, res.output
    data = json.loads(res.stdout)
    assert data["arcsec"] == 10 and data["pixel"] == 0 and data["band"] == "red"
    assert list(data["cameras"]) == list(CAMERAS)
    for cam in CAMERAS:
        for ang in ("yaw", "pitch", "roll"):
            assert set(data["cameras"][cam][ang]) == {"along_m", "cross_m"}


def test_sensitivity_table():
    res = runner.invoke(app, ["sensitivity", "--ephemeris-m", "50"])
    assert res.exit_code == 0
    assert "Df" in res.stdout and "radial" in res.stdout and "position error" in res.stdout


@pytest.mark.parametrize(
    "args, field",
    [(["--band", "rde"], "band"), (["--pixel", "1504"], "pixel"), (["--pixel", "-1"], "pixel")],
)
def test_bad_input_one_line_exit_2(args, field):
    proc = subprocess.run(
        [sys.executable, "-m", "misrgraph.commands.cli", "sensitivity", *args], capture_output=True, text=True
    )
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1, proc.stderr
    assert lines[0].startswith(f"misrgraph: error: {field}:")
    assert "Traceback" not in proc.stderr
    if field == "band":
        assert "blue, green, red, nir" in lines[0]
