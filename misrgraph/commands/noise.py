"""``misrgraph noise``: the noise model, every level the estimator assumes, and where it comes from."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer
from rich.table import Table

from misrgraph.commands.common import check_output, console, handle_errors, print_json

__all__ = ["app", "noise_init", "noise_show"]

app = typer.Typer(
    help="The noise model: every level the estimator assumes (attitude, jitter, ephemeris, camera, DEM).",
    no_args_is_help=True,
)


@app.command("init")
@handle_errors
def noise_init(
    out: Path = typer.Option(..., "--out", help="Noise-model file to write (JSON), with the pre-flight defaults."),
) -> None:
    """Write the pre-flight noise model to a file, to edit and give to --noise-model."""
    from misrgraph.io.noise import save_noise_model
    from misrgraph.model.noise import NoiseModel

    check_output(out, "--out")
    save_noise_model(NoiseModel(), out)
    console.print(f"pre-flight noise model -> {out}", highlight=False)


@app.command("show")
@handle_errors
def noise_show(
    file: Optional[Path] = typer.Argument(None, help="A noise-model file. Default: the pre-flight model."),
    as_json: bool = typer.Option(False, "--json", help="Print the levels as JSON."),
) -> None:
    """Print every level of a noise model with its unit and where it comes from."""
    from misrgraph.io.noise import read_noise_model
    from misrgraph.model.noise import LEVELS, NoiseModel

    if file is None:
        model, source = NoiseModel(), {}
    else:
        model, source = read_noise_model(file)
    rows = []
    for (section, name), (unit, default_source) in LEVELS.items():
        value = getattr(getattr(model, section), name)
        value = [float(f"{x:.6g}") for x in value] if isinstance(value, tuple) else float(f"{value:.6g}")
        origin = source.get(section, "pre-flight")
        rows.append(
            {
                "level": f"{section}.{name}",
                "value": value,
                "unit": unit,
                "source": default_source if origin == "pre-flight" else origin,
            }
        )
    if as_json:
        print_json({"file": str(file) if file else None, "levels": rows})
        return
    table = Table(title=f"noise model: {file or 'pre-flight defaults'}")
    for col in ("level", "value", "unit", "where it comes from"):
        table.add_column(col)
    for r in rows:
        table.add_row(r["level"], str(r["value"]) if r["value"] != [] else "(from the value)", r["unit"], r["source"])
    console.print(table)
