"""The ``misrgraph`` command line: the root application and its commands, one module per group.

Each command is a thin wrapper over a ``run_*`` function that notebooks import too. Every command
turns a :class:`~misrgraph.errors.MisrGraphError` into a one-line message on stderr and an exit
status (:mod:`misrgraph.commands.common`); ``--json`` prints machine-readable output on stdout.
"""

from __future__ import annotations

import typer

from misrgraph.commands import (
    adjust,
    bench,
    calibrate,
    campaign,
    cgm,
    demo,
    imports,
    info,
    match,
    monitor,
    noise,
    products,
    sensitivity,
    simulate,
    som,
    update,
    view,
)
from misrgraph.commands.common import (
    configure_logging,
    exit_hard_on_output_errors,
    set_debug,
)

__all__ = ["app", "main"]

app = typer.Typer(
    add_completion=False,
    no_args_is_help=True,
    pretty_exceptions_show_locals=False,
    help="In-flight geometric calibration of MISR as a GTSAM factor graph.",
)


@app.callback()
def _root(
    verbose: bool = typer.Option(False, "--verbose", "-v", help="Log progress details on stderr."),
    debug: bool = typer.Option(False, "--debug", help="Show the full traceback of an error instead of one line."),
) -> None:
    set_debug(debug)
    configure_logging(verbose)


# the workflow, in the order a user meets it
app.command()(simulate.simulate)
app.command()(match.match)
app.command()(calibrate.calibrate)
app.command()(adjust.adjust)
app.command("tie-height")(adjust.tie_height)
app.command()(update.update)
app.command()(products.products)
app.command(help=campaign.CAMPAIGN_HELP)(campaign.campaign)
app.command()(view.view)
app.command()(info.info)
app.command(help=sensitivity.SENS_HELP)(sensitivity.sensitivity)
app.command()(demo.demo)
app.command()(monitor.monitor)
app.add_typer(som.app, name="som")
app.add_typer(imports.app, name="import")
app.add_typer(noise.app, name="noise")
app.add_typer(cgm.app, name="cgm")
app.add_typer(bench.app, name="bench")


def main() -> None:
    """Console-script entry point."""
    exit_hard_on_output_errors()
    app()


if __name__ == "__main__":  # pragma: no cover
    main()
