"""``misrgraph update``: the incremental (iSAM2) state of a path's passes."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from misrgraph.commands.common import (
    CONFIG_HELP,
    NOISE_HELP,
    adjust_config,
    check_output,
    console,
    err_console,
    fail,
    handle_errors,
    print_json,
)

__all__ = ["update"]


@handle_errors
def update(
    state: Path = typer.Argument(..., help="State directory (created on first use)."),
    passes: Optional[list[Path]] = typer.Argument(None, help="New pass files (HDF5) to add, in order."),
    camera_model: Optional[Path] = typer.Option(
        None,
        "--camera-model",
        help="Camera model HDF5, 'preflight', 'nominal', or a CGM store (misrgraph cgm): the version valid for the "
        "first pass's orbit, and every pass of the state must be in its range (needed when creating the state).",
    ),
    gcp_file: Optional[Path] = typer.Option(None, "--gcps", help="GCP database (needed when creating the state)."),
    dem_file: Optional[Path] = typer.Option(None, "--dem", help="DEM tiles (recommended when creating the state)."),
    compare_batch: bool = typer.Option(
        False,
        "--compare-batch",
        help="Also re-solve all passes in batch and report the cost ratio and the difference in sigma.",
    ),
    report: Optional[str] = typer.Option(
        None, "--report", help="Also report error models, marginals and scores of this earlier pass id."
    ),
    linearization_tol: Optional[float] = typer.Option(
        None,
        "--linearization-tol",
        min=1e-6,
        help="Re-linearise until the linear model's error is at most this many sigma (smaller: closer to the optimum, "
        "slower). Default: 0.01.",
    ),
    observations: Optional[str] = typer.Option(
        None,
        "--observations",
        help="simulated (each pass's observations) or matched (those 'misrgraph match' measured). Fixed when the "
        "state is created (default: simulated); a later update may repeat it, not change it.",
    ),
    config: Optional[Path] = typer.Option(
        None, "--config", help=CONFIG_HELP.format(cls="AdjustConfig") + " Fixed when the state is created."
    ),
    noise_model: Optional[Path] = typer.Option(
        None, "--noise-model", help=NOISE_HELP + " Fixed when the state is created."
    ),
    noise_fit: Optional[Path] = typer.Option(
        None,
        "--noise-fit",
        help="After the update, learn the attitude and ephemeris noise levels from every pass of the state and write "
        "them to this noise-model file (JSON) for --noise-model of a new state, adjust or campaign; the state keeps "
        "its own levels.",
    ),
    as_json: bool = typer.Option(False, "--json", help="Print the summaries as JSON."),
) -> None:
    """Add passes to a persistent state and re-solve incrementally with iSAM2 (crash- and restart-safe)."""
    import numpy as np

    from misrgraph.runs.update import run_update

    # None: a new state takes the defaults, an existing one keeps its own
    cfg = adjust_config({}, config, noise_model) if config is not None or noise_model is not None else None
    if not passes and report is None and noise_fit is None:
        fail("PASSES: give new pass files to add, --report PASS_ID for an earlier pass, or --noise-fit FILE")
    if noise_fit is not None:
        check_output(noise_fit, "--noise-fit")
    with err_console.status("updating...") as st:
        out = run_update(
            state,
            [str(p) for p in passes or []],
            camera_model,
            gcp_file,
            dem_file,
            cfg=cfg,
            compare_batch=compare_batch,
            progress=lambda m: st.update(m),
            report=report,
            linearization_tol=linearization_tol,
            observations=observations,
            noise_fit=noise_fit,
        )  # None: the library default
    if as_json:
        print_json(out)
        return
    console.print(f"state {out['state']}: {out['passes_in_state']} passes ({out['observation_set']} observations)")
    if "report" in out:
        r = out["report"]
        console.print(
            f"{r['pass_id']}: knots kept/removed "
            + ", ".join(f"{a} {v['kept']}/{v['removed']}" for a, v in r["knots"].items())
            + "; mean knot sigma (arcsec) "
            + ", ".join(f"{a} {np.mean(v):.2f}" for a, v in r["attitude_knot_sigma_arcsec"].items())
        )
    for u in out["updates"]:
        if u["status"] != "added":
            console.print(f"{u['pass_id']}: {u['status']}")
            continue
        line = (
            f"{u['pass_id']}: added in {u['update_seconds']:.2f} s "
            f"({u['relinearization_rounds']} re-linearisation rounds)"
        )
        if "batch" in u:
            b = u["batch"]
            line += (
                f"; batch re-solve {b['seconds']:.2f} s (update/batch {b['ratio_update_over_batch']:.2f}), "
                f"max difference {b['max_difference_in_sigma']:.1e} sigma"
            )
        console.print(line)
        th, to = u["tie_height"], u["tie_offset"]
        if th["source"] != "off" or to["source"] != "off":
            console.print(
                f"   tie points: shared height error {th['sigma_m']:.1f} m ({th['source']}), conjugates' shared offset "
                f"{to['sigma_px']:.3f} px ({to['source']}), both in their covariance"
            )
        if "nees" in u:
            console.print(
                f"   NEES/dim knots {u['nees']['knots']:.2f}, landmarks {u['nees']['landmarks']:.2f}; "
                "attitude RMS where observed (arcsec) "
                + ", ".join(f"{k} {v:.1f}" for k, v in u["attitude_rms_arcsec_observed"].items())
            )
    if "noise_fit" in out:
        nf = out["noise_fit"]
        learned = [k for k, v in nf["levels"].items() if v.get("applied")]
        console.print(
            f"noise levels from {nf['passes']} passes -> {nf['out']}: "
            + (", ".join(learned) if learned else "none learned (the state's levels kept)"),
            highlight=False,
        )
