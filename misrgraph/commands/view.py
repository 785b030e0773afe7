"""``misrgraph view``: results and camera models in the rerun viewer."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from misrgraph.commands.common import (
    console,
    handle_errors,
)

__all__ = ["view"]


@handle_errors
def view(
    result: Path = typer.Argument(
        ..., help="RESULT.h5 from adjust, a camera model written by calibrate, or a campaign directory over years."
    ),
    save: Optional[Path] = typer.Option(None, "--save", help="Write a .rrd recording."),
    spawn: bool = typer.Option(False, "--spawn", help="Open the rerun viewer."),
    exaggeration: float = typer.Option(200.0, "--exaggeration", help="Scale of the 3-sigma landmark ellipsoids."),
) -> None:
    """Inspect covariances and residuals in the rerun viewer (entity paths: see misrgraph.viz.viewer)."""
    from misrgraph.viz.viewer import run_view

    out = run_view(result, save, spawn, exaggeration)
    console.print(
        f"logged {len(out['entities'])} entities ({out['kind']})" + (f" to {out['rrd']}" if out["rrd"] else "")
    )
