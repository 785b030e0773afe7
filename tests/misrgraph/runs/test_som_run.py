"""``misrgraph som convert`` and ``som orbit``: every form from any one, JSON keys, clear errors."""

from __future__ import annotations

import json

import pytest
from typer.testing import CliRunner

from misrgraph.commands.cli import app
from misrgraph.runs.som import run_som_convert, run_som_orbit

KEYS = {"path", "resolution_m", "block", "line", "sample", "lat", "lon", "som_x", "som_y"}


def _json(args: list[str]) -> dict:
    res = CliRunner().invoke(app, args + ["--json"])
    assert res.exit_code == 0, res.output
    return json.loads(res.stdout)


def test_convert_from_each_form_agrees() -> None:
    # MtkBlsToLatLon's second case, entered in each of the three forms
    a = _json(
        [
            "som",
            "convert",
            "--path",
            "189",
            "--resolution",
            "275",
            "--block",
            "1",
            "--line",
            "127.5",
            "--sample",
            "1023.5",
        ]
    )
    assert KEYS <= set(a)
    assert abs(a["lat"] - 65.821183366596) < 1e-6 and abs(a["lon"] - 173.816760521356) < 1e-6
    assert abs(a["som_x"] - 7495949.999777129851) < 0.01 and abs(a["som_y"] - 809049.999353842111) < 0.01
    b = _json(
        ["som", "convert", "--path", "189", "--resolution", "275", "--lat", str(a["lat"]), "--lon", str(a["lon"])]
    )
    c = _json(
        [
            "som",
            "convert",
            "--path",
            "189",
            "--resolution",
            "275",
            "--som-x",
            str(a["som_x"]),
            "--som-y",
            str(a["som_y"]),
        ]
    )
    for other in (b, c):
        assert other["block"] == 1
        assert abs(other["line"] - 127.5) < 1e-3 and abs(other["sample"] - 1023.5) < 1e-3
        assert abs(other["som_x"] - a["som_x"]) < 0.01 and abs(other["lat"] - a["lat"]) < 1e-6


def test_convert_off_the_grid_gives_null_block() -> None:
    out = run_som_convert(189, 275, lat=32.0, lon=90.0)
    assert out["block"] is None and out["on_grid"] is False
    assert abs(out["som_x"] - 11640816.350309696048) < 0.01


def test_orbit_by_number_and_by_time() -> None:
    assert _json(["som", "orbit", "--orbit", "30000"]) == {
        "orbit": 30000,
        "path": 197,
        "start": "2005-08-08T10:10:00Z",
        "end": "2005-08-08T11:48:53Z",
    }
    by_time = _json(["som", "orbit", "--time", "2006-09-24T10:35:30Z"])
    assert (by_time["orbit"], by_time["path"]) == (36000, 201)
    assert run_som_orbit(time=by_time["start"])["orbit"] == 36000


@pytest.mark.parametrize(
    "args,field",
    [
        (["som", "convert", "--path", "1", "--lat", "10"], "point"),
        (
            [
                "som",
                "convert",
                "--path",
                "1",
                "--lat",
                "10",
                "--lon",
                "3",
                "--block",
                "2",
                "--line",
                "0",
                "--sample",
                "0",
            ],
            "point",
        ),
        (["som", "convert", "--path", "0", "--lat", "10", "--lon", "3"], "path"),
        (["som", "convert", "--path", "1", "--resolution", "300", "--lat", "10", "--lon", "3"], "resolution_m"),
        (["som", "convert", "--path", "1", "--block", "1", "--line", "0", "--sample", "600"], "sample"),
        (["som", "orbit"], "orbit/time"),
        (["som", "orbit", "--orbit", "100"], "orbit"),
        (["som", "orbit", "--time", "yesterday"], "--time"),
    ],
)
def test_bad_input_is_one_line_and_exit_2(args, field) -> None:
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 2
    assert f"error: {field}" in res.output and "Traceback" not in res.output
