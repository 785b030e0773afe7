"""``misrgraph bench report``: the results pages and the README's figures are rendered from the
stored bench results, byte for byte, and a bench result carries the command that produced it."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
import typer
from typer.testing import CliRunner

from misrgraph.bench.provenance import finish, source_commit
from misrgraph.bench.report import ReportConfig, render_report, run_report
from misrgraph.commands.cli import app
from misrgraph.errors import FileFormatError

ROOT = Path(__file__).resolve().parents[3]
runner = CliRunner()


def _repo_config() -> ReportConfig:
    return ReportConfig(data=ROOT / "docs/results/data", pages=ROOT / "docs/results", readme=ROOT / "README.md")


def test_the_stored_pages_are_what_the_data_render():
    """Every generated page and README block on disk equals its rendering: a figure typed in by
    hand, or data changed without re-rendering, fails here."""
    res = run_report(_repo_config(), check=True)
    assert res["changed"] == [], f"out of date (run 'misrgraph bench report'): {res['changed']}"
    assert any(p.endswith("README.md") for p in res["files"])


def test_rendering_is_a_pure_function_of_the_data(tmp_path):
    data = tmp_path / "data"
    shutil.copytree(ROOT / "docs/results/data", data)
    readme = tmp_path / "README.md"
    readme.write_text((ROOT / "README.md").read_text())
    cfg = ReportConfig(data=data, pages=tmp_path / "pages", readme=readme)
    first = run_report(cfg)
    assert first["changed"]  # everything is new here
    again = render_report(cfg)
    assert all(p.read_text() == text for p, text in again.items())
    assert run_report(cfg, check=True)["changed"] == []
    # a figure edited by hand in a page is found
    page = next((tmp_path / "pages").glob("*.md"))
    page.write_text(page.read_text().replace("|", "| ", 1))
    assert str(page) in run_report(cfg, check=True)["changed"]


def test_a_page_names_its_command_commit_and_machine(tmp_path):
    data = tmp_path / "data"
    data.mkdir()
    result = {
        "provenance": {
            "command": "misrgraph bench solver --tie-points 50",
            "bench": "solver",
            "commit": "0123456789ab",
            "machine": {
                "cpu": "CPU X",
                "cores": 2,
                "memory_gib": 8.0,
                "os": "Linux",
                "python": "3.11",
                "numpy": "2.0",
                "gtsam": "4.3",
            },
        },
        "variables": 10,
        "factors": 20,
        "observations": 30,
        "ratio_gtsam_lm_over_core": 4.25,
        "core": {"seconds": 1.0, "iterations": 5, "seconds_per_iteration": 0.2, "final_cost": 1.5},
        "gtsam_lm": {"seconds": 4.25, "iterations": 5, "seconds_per_iteration": 0.85, "final_cost": 1.5},
    }
    (data / "solver.json").write_text(json.dumps(result))
    pages = render_report(ReportConfig(data=data, pages=tmp_path, readme=None))
    text = pages[tmp_path / "solver.md"]
    for needle in (
        "`misrgraph bench solver --tie-points 50`",
        "`0123456789ab`",
        "CPU X, 2 cores",
        "| core | 1.00 | 5 |",
        "gtsam_lm / core: 4.2x",
    ):
        assert needle in text, needle


def test_bad_stored_results_are_named(tmp_path):
    data = tmp_path / "data"
    data.mkdir()
    (data / "x.json").write_text("{not json")
    with pytest.raises(FileFormatError, match="x.json: not JSON"):
        render_report(ReportConfig(data=data, pages=tmp_path, readme=None))
    (data / "x.json").write_text(json.dumps({"runs": 3}))
    with pytest.raises(FileFormatError, match="no 'provenance'"):
        render_report(ReportConfig(data=data, pages=tmp_path, readme=None))
    res = runner.invoke(app, ["bench", "report", "--data", str(tmp_path / "none"), "--readme", "-"])
    assert res.exit_code == 2 and "--data" in res.stderr


def test_check_exits_1_when_out_of_date(tmp_path):
    data = tmp_path / "data"
    shutil.copytree(ROOT / "docs/results/data", data)
    args = ["bench", "report", "--data", str(data), "--pages", str(tmp_path / "pages"), "--readme", "-"]
    res = runner.invoke(app, [*args, "--check"])
    assert res.exit_code == 1 and "out of date" in res.stderr
    assert runner.invoke(app, args).exit_code == 0
    assert runner.invoke(app, [*args, "--check"]).exit_code == 0


def test_provenance_is_the_command_as_typed(tmp_path):
    """``finish`` inside a command records the subcommand path and the options given on the
    command line (not the defaults), the commit and the machine, and ``--save`` writes it."""
    mini = typer.Typer()
    out = tmp_path / "r.json"

    @mini.command()
    def study(
        runs: int = typer.Option(3, "--runs"),
        seed: int = typer.Option(0, "--seed"),
        quick: bool = typer.Option(False, "--quick"),
    ) -> None:
        finish({"runs": runs}, out)

    @mini.command()
    def other() -> None:  # a second command makes 'study' a subcommand, as in misrgraph bench
        pass

    res = runner.invoke(mini, ["study", "--runs", "7", "--quick"])
    assert res.exit_code == 0, res.output
    stored = json.loads(out.read_text())
    p = stored["provenance"]
    assert p["command"] == "misrgraph study --runs 7 --quick"
    assert p["bench"] == "study" and stored["runs"] == 7
    assert p["commit"] == source_commit() and p["machine"]["cores"] >= 1
    assert list(stored)[0] == "provenance"
