"""``misrgraph match``: GCPs and tie points measured in a scenario's imagery."""

from __future__ import annotations

from pathlib import Path
from typing import Any, Optional

import typer
from rich.table import Table

from misrgraph.commands.common import (
    CONFIG_HELP,
    console,
    err_console,
    handle_errors,
    merge_config,
    print_json,
)

__all__ = ["match"]


@handle_errors
def match(
    scenario_dir: Path = typer.Argument(..., help="Scenario directory with imagery (misrgraph simulate --imagery)."),
    pass_file: Optional[Path] = typer.Option(
        None, "--pass", help="Match only this pass file (default: every pass with imagery)."
    ),
    search: Optional[int] = typer.Option(
        None,
        "--search-px",
        help="Search range (px) each side of the predicted position; it must cover the navigation's 3-sigma error. "
        "Default: the range the windows were rendered for.",
    ),
    min_cameras: int = typer.Option(
        3, "--min-cameras", help="Keep a tie point matched in at least this many cameras (An included)."
    ),
    config: Optional[Path] = typer.Option(None, "--config", help=CONFIG_HELP.format(cls="MatchConfig")),
    as_json: bool = typer.Option(False, "--json", help="Print the summary as JSON."),
) -> None:
    """Measure GCPs and tie points in the imagery and write them into each pass file.

    GCPs: chip NCC and least-squares matching; tie points: An's interest points matched in the other
    cameras. The measurements sit beside the simulated observations ('adjust --observations matched').
    """
    from misrgraph.match.pipeline import MatchConfig
    from misrgraph.runs.match import run_match

    fields: dict[str, Any] = dict(search_px=search, min_cameras=min_cameras)
    merge_config(fields, config)
    cfg = MatchConfig.from_dict(fields)
    with err_console.status("matching...") as st:
        res = run_match(scenario_dir, cfg, pass_file, progress=lambda s: st.update(s))
    out = {k: v for k, v in res.items() if k != "passes"}
    if as_json:
        print_json(out)
        return
    t = Table(title=f"matching in {scenario_dir}")
    for col in (
        "kind",
        "candidates",
        "matched",
        "error RMS (px)",
        "error p95 (px)",
        "error / sigma RMS",
        "error / sigma RMS, correct matches",
        "wrong",
        "s",
    ):
        t.add_column(col, justify="right")
    for kind in ("gcp", "tie"):
        v = out[kind]
        e = v.get("error_px") or {}

        def fmt(x):
            return f"{x:.3f}" if isinstance(x, float) else "-"

        t.add_row(
            kind,
            str(v["candidates"]),
            str(v["matched"]),
            fmt(e.get("rms")),
            fmt(e.get("p95")),
            fmt(v.get("normalised_error_rms")),
            fmt(v.get("normalised_error_rms_correct")),
            str(v.get("wrong_matches", "-")),
            f"{v['seconds']:.1f}",
        )
    console.print(t)
    for p in res["passes"]:
        scales = (p.get("tie") or {}).get("sigma_scale")
        if scales:
            console.print(
                f"{p['pass_id']} tie sigma scale (redundancy): "
                + ", ".join(
                    f"{c} {v['scale']:.2f} ({v['redundancy']:.0f}"
                    + ("" if v["estimated"] else f", {v['scale_from']}'s" if "scale_from" in v else ", LSM sigma kept")
                    + ")"
                    for c, v in scales.items()
                ),
                soft_wrap=True,
                highlight=False,
            )
        g = (p.get("gcp") or {}).get("sigma_scale")
        if g:
            console.print(
                f"{p['pass_id']} GCP sigma scale (redundancy): {g['scale']:.2f} ({g['redundancy']:.0f}"
                + ("" if g["estimated"] else ", LSM sigma kept")
                + ")",
                soft_wrap=True,
                highlight=False,
            )
