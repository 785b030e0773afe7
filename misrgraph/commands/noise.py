"""``misrgraph noise``: the noise model, every level the estimator assumes, and where it comes from."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer
from rich.table import Table

from misrgraph.commands.common import check_output, console, handle_errors, print_json

__all__ = ["app", "noise_init", "noise_show", "noise_fit"]

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


def _in_model(level: dict) -> str:
    """The fit table's "in the model" cell: yes, or why the base's level stays."""
    if level.get("applied", True):
        return "yes"
    z = level.get("z")
    why = {
        "not determined": "not determined",
        "agrees with the base": "agrees with the base" + (f", z {z:+.1f}" if z is not None else ""),
        "the base's shape": "the base's shape",
    }.get(level.get("reason", ""), level.get("reason", ""))
    return f"no ({why})"


@app.command("fit")
@handle_errors
def noise_fit(
    results: list[Path] = typer.Argument(..., help="RESULT.h5 files of 'misrgraph adjust --out', one per pass."),
    out: Optional[Path] = typer.Option(
        None, "--out", help="Noise-model file to write (JSON), for --noise-model of adjust, update, products, campaign."
    ),
    base: Optional[Path] = typer.Option(
        None, "--base", help="Noise-model file whose levels the passes do not carry are kept. Default: pre-flight."
    ),
    learn_shape: Optional[bool] = typer.Option(
        None,
        "--learn-attitude-shape/--keep-attitude-shape",
        help="Apply the attitude process's fitted natural frequency (the rate's sigma over the value's) always, or "
        "never. Default: per angle, when the passes reject the base's for a faster process (some angle's z > "
        "3.29, then each angle's z > 1.96), which then also gets denser knots.",
        show_default=False,
    ),
    as_json: bool = typer.Option(False, "--json", help="Print the fitted levels as JSON."),
) -> None:
    """Learn the noise levels from adjusted passes: attitude, ephemeris, observation and DEM scales.

    The attitude sigma per angle and the ephemeris offset and drift sigmas maximise the passes'
    marginal likelihood of their prior, each with a 1 sigma from the likelihood's curvature; a
    level the passes do not determine, or whose base level they do not reject (|z| <= 1.96), keeps
    the base's, and the attitude's shape (rate over value) stays the base's unless the passes
    reject it for a faster one, which gets knots that miss no more of it than of the jitter.
    The tie-point, GCP and DEM sigma scales come from the passes' variance components. Jitter,
    the attitude damping, the camera prior and the once-per-revolution term are not fitted and
    keep the base's levels.
    """
    from misrgraph.runs.noise import run_noise_fit

    if out is not None:
        check_output(out, "--out")
    res = run_noise_fit(results, out, base, learn_shape)
    if as_json:
        print_json(res)
        return
    table = Table(title=f"noise levels learned from {res['passes']} passes")
    for col in ("level", "learned", "+-1 sigma", "adjusted with", "unit", "in the model"):
        table.add_column(col, justify="right")
    for name, v in res["levels"].items():
        table.add_row(
            name,
            f"{v['value']:.4g}",
            "-" if v["sigma"] is None else f"{v['sigma']:.2g}",
            "-" if v["previous"] is None else f"{v['previous']:.4g}",
            v["unit"],
            _in_model(v),
        )
    console.print(table)
    console.print("not fitted (kept from the base): " + ", ".join(res["not_fitted"]), highlight=False)
    if out is not None:
        console.print(f"noise model -> {out}", highlight=False)
