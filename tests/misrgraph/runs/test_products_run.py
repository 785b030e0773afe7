"""``run_products`` over an incremental update state: PP of every pass from the state's estimate."""

from __future__ import annotations

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from misrgraph.commands.cli import app
from misrgraph.errors import InputError
from misrgraph.io.products import read_pp
from misrgraph.model.constants import CAMERAS
from misrgraph.runs.products import parse_blocks, run_products
from misrgraph.runs.update import restore_state, run_update


@pytest.fixture(scope="module")
def state(path_dir, tmp_path_factory):
    d = tmp_path_factory.mktemp("state") / "s"
    files = sorted((path_dir / "passes").glob("*.h5"))[:2]
    run_update(d, [str(f) for f in files], path_dir / "camera_model.h5", path_dir / "gcp.h5", path_dir / "dem.h5")
    return d


def test_pp_of_every_pass_of_a_state_against_truth(state, path_dir, tmp_path):
    res = run_products(state, tmp_path / "pp", default_blocks=1)
    solver, _, _ = restore_state(state)
    assert [p["pass_id"] for p in res["passes"]] == [p.pass_id for p in solver.passes]
    for row in res["passes"]:
        assert set(row["pp_error_m"]) == set(CAMERAS)
        pp = read_pp(row["files"]["pp"])
        assert pp.pass_id == row["pass_id"] and pp.blocks.tolist() == [res["blocks"][0]]
        for cam, v in row["pp_error_m"].items():
            # the state's estimate improves every camera's geolocation over the supplied navigation
            assert v["supplied_rms"] > v["rms"], (row["pass_id"], cam)
            # one pass's points share one navigation error: its scatter (chi-square of a few dof)
            assert 0.2 < v["rms_over_predicted"] < 2.5, (row["pass_id"], cam)
    assert json.loads((tmp_path / "pp" / "products.json").read_text())["state"] == str(state)
    # one pass, named by its file, from the command line; the same PP as above
    files = sorted((path_dir / "passes").glob("*.h5"))
    cli = CliRunner().invoke(
        app,
        [
            "products",
            str(state),
            "--out",
            str(tmp_path / "one"),
            "--pass",
            str(files[1]),
            "--blocks",
            str(res["blocks"][0]),
            "--json",
        ],
    )
    assert cli.exit_code == 0, cli.output
    one = json.loads(cli.stdout)["passes"]
    assert [r["pass_id"] for r in one] == [res["passes"][1]["pass_id"]]
    np.testing.assert_array_equal(read_pp(one[0]["files"]["pp"]).line0, read_pp(res["passes"][1]["files"]["pp"]).line0)
    # bad input: a pass not in the state, a directory that is not a state
    with pytest.raises(InputError, match="--pass"):
        run_products(state, tmp_path / "x", pass_file=files[5], default_blocks=1)
    with pytest.raises(InputError, match="STATE_DIR"):
        restore_state(tmp_path / "nothing")
    assert not (tmp_path / "nothing").exists()


def test_parse_blocks() -> None:
    assert parse_blocks("62-64").tolist() == [62, 63, 64]
    assert parse_blocks(" 70 ").tolist() == [70]
    assert parse_blocks((62, 63)).tolist() == [62, 63]  # the Python API's pair
    for bad in ("64-62", "0-3", "181", "a-b", (62,), 62.0, None):
        with pytest.raises(InputError, match="--blocks"):
            parse_blocks(bad)  # type: ignore[arg-type]
