"""The campaign report: ``REPORT/campaign.md`` (Markdown tables) and its PNG figures
(:func:`misrgraph.viz.plots.plot_campaign`), written atomically.

Accuracy figures are against the simulator's truth and appear only where the inputs carry one.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np

from misrgraph.errors import MisrGraphError
from misrgraph.io.h5 import atomic_file
from misrgraph.model.constants import CAMERAS

__all__ = ["write_report"]

log = logging.getLogger(__name__)


def _f(v: Any, fmt: str = ".1f") -> str:
    return "–" if v is None else format(v, fmt)


def _land_background() -> tuple[Any, tuple[float, float, float, float]] | None:
    try:
        from misrgraph.sim.terrain import land_mask
    except ImportError:
        return None
    lat = np.arange(-89.5, 90, 1.0)
    lon = np.arange(-179.5, 180, 1.0)
    try:
        mask = land_mask(*np.meshgrid(lat, lon, indexing="ij"))
    except (ImportError, MisrGraphError):  # the land-mask data is an optional extra
        return None
    return mask.astype(float), (-180.0, 180.0, -90.0, 90.0)


def write_report(
    report_dir: Path, plan: dict[str, Any], summary: dict[str, Any], records: list[dict[str, Any]]
) -> Path:
    """Write ``campaign.md`` and its figures into ``report_dir``; return the Markdown file."""
    report_dir.mkdir(parents=True, exist_ok=True)
    pts: dict[str, list[float]] = {"lat": [], "lon": [], "rms_m": []}
    for r in records:
        if r["stage"] == "adjust" and r["status"] == "done":
            for k in pts:
                pts[k].extend((r["summary"].get("checkpoint_points") or {}).get(k, []))
    figures: list[Path] = []
    try:
        from misrgraph.viz.plots import plot_campaign

        figures = plot_campaign(summary, pts, report_dir, _land_background())
    except MisrGraphError as exc:  # matplotlib is an optional extra: the tables still say everything
        log.warning("campaign report without figures: %s", exc)
    years = summary.get("years") or {}
    if years.get("status") == "done":
        try:
            from misrgraph.viz.plots import plot_camera_years

            figures += plot_camera_years(years, report_dir)
        except MisrGraphError as exc:
            log.warning("campaign report without the figure over years: %s", exc)
    cfg = plan["config"]
    L = [
        "# misrgraph campaign",
        "",
        f"{len(plan['paths'])} paths, {cfg['months']} months of data, {cfg['fraction']:.0%} of each path's repeat "
        "passes "
        f"(at least {cfg['passes_per_path']}), {cfg['size']} size, {cfg['truth']} truth; inputs: {plan['inputs']}; "
        f"{cfg.get('observations', 'simulated')} observations"
        + (" (measured in the imagery by image matching)." if cfg.get("observations") == "matched" else "."),
        f"Ran on: {summary['cluster'].get('kind')} ({summary['cluster'].get('workers')} workers) in "
        f"{summary['seconds']:.0f} s.",
        "",
        "## Passes",
        "",
        "| planned | done | failed |",
        "|---:|---:|---:|",
        f"| {summary['passes']['planned']} | {summary['passes']['done']} | {summary['passes']['failed']} |",
        "",
    ]
    if summary["failed"]:
        L += ["Failures (each reported, none stopped the others):", ""]
        L += [f"- {f['stage']} {f['name']}: {f['reason']}" for f in summary["failed"]] + [""]
    cal = summary["calibration"]
    L += ["## Calibration (GCP month)", ""]
    if cal.get("status") == "done" and cal.get("pointing_error_px"):
        L += ["| camera | pointing error (px) | 1σ (px) |", "|---|---:|---:|"]
        L += [
            f"| {c} | {_f(cal['pointing_error_px'].get(c), '.3f')} | {_f((cal.get('sigma_px') or {}).get(c), '.3f')} |"
            for c in CAMERAS
            if c in cal["pointing_error_px"]
        ]
        L += [
            "",
            f"Largest pointing error {_f(cal.get('max_pointing_error_px'), '.3f')} px (requirement 0.125); "
            f"NEES/dim {_f(cal.get('nees'), '.2f')}. File: `{cal['file']}`.",
            "",
        ]
    elif cal.get("status") == "done":
        L += [f"Camera model: `{cal['file']}` (no truth to score it against).", ""]
    else:
        L += [f"Failed: {cal.get('reason')}", ""]
    if summary["cameras"]:
        L += [
            "## Check-point accuracy per camera",
            "",
            "| camera | passes | RMS after (m) | predicted RMS (m) | supplied navigation, mean (m) |",
            "|---|---:|---:|---:|---:|",
        ]
        L += [
            f"| {c} | {v['passes']} | {_f(v['checkpoint_rms_m'])} | {_f(v['predicted_rms_m'])} | "
            f"{_f(v['supplied_mean_m'])} |"
            for c, v in summary["cameras"].items()
        ] + [""]
    L += _noise_section(summary.get("noise_fit"))
    L += _years_section(summary.get("years"))
    L += [
        "## Per path",
        "",
        "| path | passes done/planned | check-point RMS (m) | co-registration max (px) | PP error RMS (m) | ROI |",
        "|---:|---:|---:|---:|---:|---|",
    ]
    for p, v in summary["paths"].items():
        prod = v.get("products") or {}
        pp = _f(prod.get("pp_error_rms_m")) if prod.get("status") == "done" else ("failed" if prod else "not built")
        roi = prod.get("roi")
        roi_txt = (
            f"co-registration ≤ {_f(roi['coregistration_px_max'], '.2f')} px (blocks "
            f"{roi['blocks'][0]}–{roi['blocks'][1]})"
            if roi
            else "not built (campaign --roi; needs imagery)"
        )
        L.append(
            f"| {p} | {v['passes']['done']}/{v['passes']['planned']} | {_f(v['checkpoint_rms_m'])} | "
            f"{_f(v['coregistration_px_max'], '.3f')} | {pp} | {roi_txt} |"
        )
    L += [
        "",
        "## Time per stage",
        "",
        "Task seconds are summed over the workers; wall seconds run from the stage's first task "
        "start to its last task's end (stages overlap).",
        "",
        "| stage | tasks | found done | failed | task seconds | wall seconds |",
        "|---|---:|---:|---:|---:|---:|",
    ]
    L += [
        f"| {s} | {v['tasks']} | {v['found_done']} | {v['failed']} | {v['task_seconds']:.1f} | "
        f"{v['wall_seconds']:.1f} |"
        for s, v in summary["stages"].items()
    ]
    rss = summary["cluster"].get("peak_rss_mb") or {}
    if rss:
        L += ["", "Peak memory per process (MB): " + ", ".join(f"{k}: {v:.0f}" for k, v in rss.items())]
    L += [""] + [f"![{f.stem}]({f.name})" for f in figures] + [""]
    md = report_dir / "campaign.md"
    with atomic_file(md) as fh:
        fh.write("\n".join(L))
    return md


def _years_section(years: dict[str, Any] | None) -> list[str]:
    """The campaign over years: versions, alarms and the stale passes (Markdown lines)."""
    if not years:
        return []
    if years.get("status") != "done":
        return ["## Over the years", "", f"The camera-model versions failed: {years.get('reason')}", ""]
    L = [
        "## Over the years",
        "",
        f"{len(years['windows'])} calibration windows; the monitor's alarms made "
        f"{len(years['versions'])} camera-model version(s), in `{years['store']}` (`misrgraph cgm list`).",
        "",
        "| version | from window | first orbit | why |",
        "|---|---:|---:|---|",
    ]
    L += [f"| {v['id']} | {v['window'] + 1} | {v['first_orbit']} | {v['reason']} |" for v in years["versions"]]
    L += [""]
    if years["alarms"]:
        L += [
            "| alarm at window | camera | parameter | test | statistic / threshold | onset window |",
            "|---:|---|---|---|---:|---:|",
        ]
        L += [
            f"| {a['window'] + 1} | {a['camera']} | {a['parameter']} | {a['kind']} | "
            f"{a['statistic']:.2f} / {a['threshold']:.2f} | {a['onset_window'] + 1} |"
            for a in years["alarms"]
        ]
        L += [""]
    else:
        L += ["No alarm: one camera model held for the whole campaign.", ""]
    stale = years["stale_passes"]
    L += ["Passes adjusted with a model the monitoring later found stale:", ""]
    if stale:
        L += ["| pass | date | adjusted with | superseded by | change |", "|---|---|---|---|---|"]
        L += [
            f"| {r['pass_id']} | {r['date']} | {r['version']} | {r['superseded_by']} | {r['change']} |" for r in stale
        ]
    else:
        L += ["none."]
    return L + [""]


def _noise_section(fit: dict[str, Any] | None) -> list[str]:
    """The noise levels learned on the campaign's first passes (Markdown lines)."""
    if not fit:
        return []
    if fit.get("status") != "done":
        return ["## Noise levels learned", "", f"The noise fit failed: {fit.get('reason')}", ""]
    L = [
        "## Noise levels learned",
        "",
        f"Learned on {len(fit['passes'])} pass(es) ({', '.join(fit['passes'])}) and used for every other pass "
        f"and path: `{fit['file']}`.",
        "",
        "| level | learned | 1σ | the fit passes used | applied |",
        "|---|---:|---:|---:|---|",
    ]
    for name, v in fit["levels"].items():
        prev = v.get("previous")
        prev_txt = _f(prev, ".4g") if isinstance(prev, (int, float)) or prev is None else str(prev)
        applied = "yes" if v.get("applied", True) else "no"
        L.append(f"| {name} | {v['value']:.4g} | {_f(v.get('sigma'), '.2g')} | {prev_txt} | {applied} |")
    return L + [""]
