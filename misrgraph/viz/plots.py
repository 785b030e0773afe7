"""PNG plots of adjustment and calibration results (matplotlib, headless ``Agg`` backend).

Used by ``misrgraph adjust --plots DIR``, ``misrgraph calibrate --plots DIR``, the demo and the
notebooks. Every function writes atomically (temporary file, then rename) and returns the paths.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from misrgraph.errors import require_extra
from misrgraph.io.truth import read_pass_truth
from misrgraph.model.constants import ANGLES, ARCSEC, CAMERAS

__all__ = ["plot_adjustment", "plot_calibration", "plot_campaign", "plot_camera_years", "plot_match"]


def _save(fig: Any, path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.tmp.png")
    fig.savefig(tmp, dpi=110, bbox_inches="tight")
    os.replace(tmp, path)
    return path


def plot_adjustment(result_h5: str | os.PathLike[str], out_dir: str | os.PathLike[str]) -> list[Path]:
    """Attitude error vs truth with 1-sigma bands, residual histograms, check-point errors."""
    import json

    matplotlib = require_extra("matplotlib", "viz", "the figures")

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from misrgraph.model.errormodels import AttitudeErrorModel

    out = Path(out_dir)
    paths = []
    from misrgraph.io.h5 import open_h5

    with open_h5(result_h5, "adjustment_result") as f:
        summary = json.loads(f.attrs["summary_json"])
        pass_file = f["provenance"].attrs.get("pass_file")
        kt = [f[f"attitude_error/{a}/knot_times"][()] for a in ANGLES]
        kv = [f[f"attitude_error/{a}/knots"][()] for a in ANGLES]
        jc = [f[f"attitude_error/{a}/joint_covariance"][()] for a in ANGLES]
        res = f["observations/residual_px"][()]
        cam = f["observations/camera"][()]
    model = AttitudeErrorModel(kt, kv)
    truth = None
    if pass_file is not None and Path(str(pass_file)).exists():
        truth = read_pass_truth(str(pass_file))
    t = np.arange(kt[0][0], kt[0][-1], 4.096)
    est = model.evaluate(t)
    fig, axes = plt.subplots(3, 1, figsize=(9, 7), sharex=True)
    for i, (a, ax) in enumerate(zip(ANGLES, axes)):
        idx, w = model.bracket(i, t)
        rows = np.stack([2 * idx, 2 * idx + 1, 2 * idx + 2, 2 * idx + 3], 1)
        sig = np.sqrt(np.einsum("ni,nij,nj->n", w, jc[i][rows[:, :, None], rows[:, None, :]], w))
        ax.fill_between(
            t, (est[:, i] - sig) / ARCSEC, (est[:, i] + sig) / ARCSEC, alpha=0.3, label="estimate +- 1 sigma"
        )
        ax.plot(t, est[:, i] / ARCSEC, lw=1.2, label="estimate")
        ax.plot(kt[i], kv[i][:, 0] / ARCSEC, "o", ms=3, label="knots")
        if truth is not None:
            ax.plot(t, truth.attitude_error.evaluate(t)[:, i] / ARCSEC, "k--", lw=1, label="truth")
        ax.set_ylabel(f"{a} error (arcsec)")
    axes[0].legend(loc="upper right", fontsize=7, ncol=4)
    axes[-1].set_xlabel("time from pass epoch (s)")
    fig.suptitle(f"attitude error, pass {summary.get('pass_id', '')}")
    paths.append(_save(fig, out / "attitude_error.png"))
    plt.close(fig)
    fig, axes = plt.subplots(3, 3, figsize=(9, 7), sharex=True)
    for c, ax in zip(range(len(CAMERAS)), axes.ravel()):
        sel = (cam == c) & np.isfinite(res[:, 0])
        ax.hist(res[sel, 0], bins=30, alpha=0.6, label="along")
        ax.hist(res[sel, 1], bins=30, alpha=0.6, label="cross")
        ax.set_title(CAMERAS[c], fontsize=9)
    axes[0, 0].legend(fontsize=7)
    fig.supxlabel("post-fit residual (pixels)")
    paths.append(_save(fig, out / "residuals.png"))
    plt.close(fig)
    cp = summary.get("checkpoint_geolocation_m")
    if cp:
        fig, ax = plt.subplots(figsize=(8, 3.5))
        names = list(cp)
        x = np.arange(len(names))
        ax.bar(
            x - 0.2,
            [cp[n]["before"]["mean"] for n in names],
            0.4,
            yerr=[cp[n]["before"]["std"] for n in names],
            label="supplied navigation",
        )
        ax.bar(
            x + 0.2,
            [cp[n]["after"]["mean"] for n in names],
            0.4,
            yerr=[cp[n]["after"]["std"] for n in names],
            label="corrected",
        )
        ax.set_xticks(x, names)
        ax.set_ylabel("check-point error (m)")
        ax.legend()
        paths.append(_save(fig, out / "checkpoints.png"))
        plt.close(fig)
    return paths


def plot_calibration(summary: dict[str, Any], out_dir: str | os.PathLike[str]) -> list[Path]:
    """Pointing error and sigma per camera; correlation matrix."""
    matplotlib = require_extra("matplotlib", "viz", "the figures")

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = Path(out_dir)
    paths = []
    names = list(summary["cameras"])
    fig, ax = plt.subplots(figsize=(8, 3.5))
    x = np.arange(len(names))
    if all("pointing_error_px" in summary["cameras"][n] for n in names):
        ax.bar(
            x - 0.2, [summary["cameras"][n]["pointing_error_before_px"] for n in names], 0.4, label="pre-flight model"
        )
        ax.bar(x + 0.2, [summary["cameras"][n]["pointing_error_px"] for n in names], 0.4, label="recalibrated")
    ax.plot(x, [summary["cameras"][n]["sigma_px"] for n in names], "k_", ms=20, mew=2, label="predicted sigma")
    ax.axhline(0.125, color="r", ls=":", label="1/8 pixel requirement")
    ax.set_yscale("log")
    ax.set_xticks(x, names)
    ax.set_ylabel("pointing error (pixels)")
    ax.legend(fontsize=8)
    paths.append(_save(fig, out / "calibration_pointing.png"))
    plt.close(fig)
    corr = np.asarray(summary["correlation"]["matrix"])
    fig, ax = plt.subplots(figsize=(7, 6))
    im = ax.imshow(corr, cmap="RdBu_r", vmin=-1, vmax=1)
    labels = summary["correlation"]["labels"]
    ax.set_xticks(range(len(labels)), labels, rotation=90, fontsize=5)
    ax.set_yticks(range(len(labels)), labels, fontsize=5)
    fig.colorbar(im, ax=ax, label="correlation")
    paths.append(_save(fig, out / "calibration_correlation.png"))
    plt.close(fig)
    return paths


def plot_campaign(
    summary: dict[str, Any],
    points: dict[str, list[float]],
    out_dir: str | os.PathLike[str],
    land: tuple[Any, tuple[float, float, float, float]] | None = None,
) -> list[Path]:
    """The campaign report's figures (PNG): check-point RMS per camera and per path (m), a world
    map of the check points coloured by their error (``points``: ``lat``, ``lon`` deg, ``rms_m``;
    ``land``: an optional boolean image with its lon/lat extent as the background), and the
    time per stage (task seconds summed over the workers). Returns the files written."""
    matplotlib = require_extra("matplotlib", "viz", "the figures")
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = Path(out_dir)
    files = []
    cams = [c for c in CAMERAS if c in summary["cameras"]]
    if cams:
        fig, ax = plt.subplots(figsize=(7, 3.2))
        x = np.arange(len(cams))
        ax.bar(x - 0.2, [summary["cameras"][c]["checkpoint_rms_m"] or np.nan for c in cams], 0.4, label="actual RMS")
        ax.bar(x + 0.2, [summary["cameras"][c]["predicted_rms_m"] or np.nan for c in cams], 0.4, label="predicted RMS")
        ax.set_xticks(x, cams)
        ax.set_ylabel("check-point error (m)")
        ax.set_title("after adjustment, all passes")
        ax.legend()
        files.append(_save(fig, out / "cameras.png"))
        plt.close(fig)
    paths = [(p, v["checkpoint_rms_m"]) for p, v in summary["paths"].items() if v.get("checkpoint_rms_m") is not None]
    if paths:
        fig, ax = plt.subplots(figsize=(max(4, 0.4 * len(paths) + 2), 3.2))
        ax.bar([p for p, _ in paths], [v for _, v in paths])
        ax.set_xlabel("path")
        ax.set_ylabel("check-point RMS (m)")
        files.append(_save(fig, out / "paths.png"))
        plt.close(fig)
    if points.get("lat"):
        fig, ax = plt.subplots(figsize=(9, 4.6))
        if land is not None:
            ax.imshow(land[0], extent=land[1], origin="lower", cmap="Greys", vmin=0, vmax=3, interpolation="nearest")
        sc = ax.scatter(points["lon"], points["lat"], c=points["rms_m"], s=6, cmap="viridis")
        fig.colorbar(sc, ax=ax, label="check-point error, RMS over cameras (m)")
        ax.set_xlim(-180, 180)
        ax.set_ylim(-90, 90)
        ax.set_xlabel("longitude (deg)")
        ax.set_ylabel("latitude (deg)")
        files.append(_save(fig, out / "map.png"))
        plt.close(fig)
    if summary["stages"]:
        fig, ax = plt.subplots(figsize=(6, 2.8))
        names = list(summary["stages"])
        ax.barh(names, [summary["stages"][s]["task_seconds"] for s in names])
        ax.set_xlabel("task seconds (summed over workers)")
        files.append(_save(fig, out / "stages.png"))
        plt.close(fig)
    return files


def plot_match(pass_file: str | os.PathLike[str], out_dir: str | os.PathLike[str], camera: str = "Df") -> list[Path]:
    """One GCP matched in ``camera``: the reference chip, its search window with the predicted,
    matched and (simulated passes) true positions, the NCC surface, and the LSM residual. Needs
    ``misrgraph match`` to have run on the pass (for the matched position)."""
    matplotlib = require_extra("matplotlib", "viz", "the figures")
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from skimage.feature import match_template

    from misrgraph.io.imagery import read_imagery, read_matched
    from misrgraph.io.passes import OrbitPass
    from misrgraph.match.lsm import lsm, ncc_search

    cam = CAMERAS.index(camera)
    im = read_imagery(pass_file)
    m = read_matched(pass_file, with_truth=True)
    p = OrbitPass.load(pass_file)
    truth = read_pass_truth(pass_file)
    chip_of = im.chip_index()
    ks = [
        k
        for k in range(len(im.gcp))
        if im.gcp.camera[k] == cam and im.gcp.band[k] == im.band and (int(im.gcp.landmark[k]), im.band) in chip_of
    ]
    if not ks:
        from misrgraph.errors import InputError

        raise InputError("camera", camera, f"a camera whose GCP windows have chips in {pass_file}")
    k = ks[0]
    row = int(im.gcp.landmark[k])
    window = im.gcp.pixels[k].astype(float)
    chip = im.chips[chip_of[(row, im.band)], cam].astype(float)
    cc = match_template(window, chip)
    peak = ncc_search(window, chip)
    res = lsm(window, chip, peak.row, peak.col) if peak is not None else None
    fig, ax = plt.subplots(1, 4, figsize=(16, 4.2))
    ax[0].imshow(chip, cmap="gray")
    ax[0].set_title(f"reference chip ({camera}, GCP row {row})")
    ax[1].imshow(window, cmap="gray")
    if res is not None:
        ax[1].plot(
            res.col, res.row, "r+", ms=14, label=f"matched (sigma {np.hypot(res.sigma_row, res.sigma_col):.3f} px)"
        )
    if truth is not None:
        geo = truth.geometry(p)
        ip = geo.ground_to_pixel(cam, int(im.gcp.band[k]), truth.landmark_ecef[row][None], continuous=True)
        ax[1].plot(ip.sample[0] - im.gcp.sample0[k], ip.line[0] - im.gcp.line0[k], "gx", ms=12, label="truth")
    ax[1].legend(loc="lower right", fontsize=8)
    ax[1].set_title("search window (line down, sample across)")
    half = (chip.shape[0] - 1) / 2
    ax[2].imshow(
        cc, cmap="viridis", extent=(half - 0.5, half + cc.shape[1] - 0.5, half + cc.shape[0] - 0.5, half - 0.5)
    )
    ax[2].set_title(f"NCC surface (peak {peak.value:.2f}, ratio {peak.ratio:.2f})" if peak else "NCC surface")
    if res is not None:
        from scipy import ndimage

        rr, qq = np.meshgrid(
            np.arange(chip.shape[0]) - half + res.row, np.arange(chip.shape[1]) - half + res.col, indexing="ij"
        )
        warped = ndimage.map_coordinates(window, [rr, qq], order=3)
        fit = np.polyval(np.polyfit(chip.ravel(), warped.ravel(), 1), chip)
        resid = warped - fit
        lim = float(np.max(np.abs(resid)))
        ax[3].imshow(resid, cmap="RdBu", vmin=-lim, vmax=lim)
        ax[3].set_title(f"LSM residual (RMS {np.std(resid):.0f} counts)")
    for a in ax:
        a.set_xticks([])
        a.set_yticks([])
    fig.suptitle(f"{p.pass_id}: {len(m.observations)} matched observations")
    out = [_save(fig, Path(out_dir) / f"match_{camera}.png")]
    plt.close(fig)
    return out


def plot_camera_years(years: dict[str, Any], out_dir: str | os.PathLike[str]) -> list[Path]:
    """The campaign over years' figure (``camera_years.png``): per camera, its calibrated
    ``delta``, ``beta`` and ``epsilon`` (arcsec, less their first window's value) at each window's
    start date with 1-sigma bands, the camera-model versions' first windows as vertical lines and
    each alarm as a cross on the parameter that raised it. ``years``: the campaign summary's
    ``years`` entry. Returns the file written."""
    matplotlib = require_extra("matplotlib", "viz", "the figures")
    matplotlib.use("Agg")
    import datetime as _dt

    import matplotlib.pyplot as plt

    dates = [_dt.date.fromisoformat(w["start"]) for w in years["windows"]]
    fig, axes = plt.subplots(3, 3, figsize=(11, 7.5), sharex=True)
    colours = {"delta": "C0", "beta": "C1", "epsilon": "C2"}
    for ax, cam in zip(axes.ravel(), CAMERAS):
        for par, c in colours.items():
            e = years["series"][cam][par]
            y = np.asarray(e["value_arcsec"]) - e["value_arcsec"][0]
            sd = np.asarray(e["sigma_arcsec"])
            ax.plot(dates, y, "o-", ms=3, color=c, label=par)
            ax.fill_between(dates, y - sd, y + sd, color=c, alpha=0.2)
        for v in years["versions"][1:]:
            ax.axvline(dates[v["window"]], color="k", ls="--", lw=0.8)
        for a in years["alarms"]:
            if a["camera"] == cam:
                e = years["series"][cam][a["parameter"]]
                ax.plot(dates[a["window"]], e["value_arcsec"][a["window"]] - e["value_arcsec"][0], "kx", ms=9)
        ax.set_title(cam, fontsize=9)
        ax.tick_params(labelsize=7)
    axes[0, 0].legend(fontsize=7)
    for ax in axes[:, 0]:
        ax.set_ylabel("change (arcsec)", fontsize=8)
    fig.autofmt_xdate()
    fig.suptitle("calibrations per window (1σ bands); dashed: a new camera-model version; x: the alarm")
    path = _save(fig, Path(out_dir) / "camera_years.png")
    plt.close(fig)
    return [path]
