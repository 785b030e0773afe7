"""Covariance and residual inspection in the rerun viewer (``misrgraph view``).

Entity paths (units in brackets; timeline ``pass_time`` = seconds from the pass epoch):

=====================================  =======================================================
``world/globe``                        latitude/longitude graticule every 10 deg (ECEF m)
``world/orbit``                        spacecraft track (supplied navigation, ECEF m)
``world/footprints/<camera>``          swath line of each camera every 30 s (on ``pass_time``)
``world/landmarks/<kind>``             estimated tie points / GCPs, check points (truth) [m]
``world/landmarks/<kind>/ellipsoids``  3-sigma covariance ellipsoids, half sizes multiplied by
                                       ``exaggeration`` (default 200, in the entity's label)
``attitude/<angle>/{estimate,upper,lower,truth}``  error estimate, +-1 sigma band, truth [arcsec]
``attitude/<angle>/knots``             knot values [arcsec] at the knot times
``attitude/<angle>/removed_knots``     removed knots (eqs. 28-29) marked at 0 on their times
``ephemeris/<axis>/{estimate,upper,lower,truth}``  ephemeris error along/cross/nadir [m]
``residuals/<camera>/{along,cross}``   post-fit residuals at the observation times [pixel]
``residuals/<camera>/histogram``       histogram of the residual norm (0.05 px bins)
``calibration/<camera>/corrections``   corrections [arcsec] (calibration results)
``calibration/<camera>/sigma``         their 1 sigma [arcsec]
``calibration/correlation``            correlation matrix across parameters and cameras
``years/<camera>/<angle>/{value,upper,lower}``  a campaign over years: each window's calibrated
                                       angle and its +-1 sigma band [arcsec], on the ``date``
                                       timeline (the window's first day)
``years/versions``, ``years/alarms``   the camera-model versions and the monitor's alarms (text,
                                       at their windows' dates)
=====================================  =======================================================
"""

from __future__ import annotations

import logging
import os
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from misrgraph.errors import FileFormatError, InputError, require_extra
from misrgraph.io.camera import read_camera_group
from misrgraph.io.h5 import open_h5, read_attr, read_dataset
from misrgraph.io.truth import read_pass_truth
from misrgraph.model.constants import ANGLES, ARCSEC, CAMERAS
from misrgraph.model.frames import geodetic_to_ecef

__all__ = ["run_view", "ellipsoid_axes", "DEFAULT_EXAGGERATION"]

log = logging.getLogger(__name__)
DEFAULT_EXAGGERATION = 200.0
KIND_COLORS = {"tie": [80, 160, 255], "gcp": [255, 80, 80], "check": [80, 220, 120]}


def ellipsoid_axes(cov: np.ndarray, n_sigma: float = 3.0, exaggeration: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Half sizes ``(N, 3)`` and rotation quaternions ``(N, 4)`` (xyzw) of n-sigma ellipsoids of ``cov (N, 3, 3)``."""
    from scipy.spatial.transform import Rotation

    w, v = np.linalg.eigh(cov)
    v = np.where(np.linalg.det(v)[:, None, None] < 0, v * np.array([1, 1, -1]), v)
    half = n_sigma * np.sqrt(np.maximum(w, 0.0)) * exaggeration
    return half, Rotation.from_matrix(v).as_quat()


def _graticule(step: float = 10.0) -> list[np.ndarray]:
    lines = []
    for lat in np.arange(-80, 81, step):
        lon = np.linspace(-180, 180, 181)
        lines.append(geodetic_to_ecef(np.full(lon.size, lat), lon, 0.0))
    for lon in np.arange(-180, 180, step):
        lat = np.linspace(-90, 90, 91)
        lines.append(geodetic_to_ecef(lat, np.full(lat.size, lon), 0.0))
    return lines


def _log_series(rec, rr, path: str, t: np.ndarray, y: np.ndarray) -> None:
    rec.send_columns(
        path,
        indexes=[rr.TimeColumn("pass_time", duration=np.asarray(t, float))],
        columns=rr.Scalars.columns(scalars=np.asarray(y, float)),
    )


def _view_adjustment(
    rec, rr, f: h5py.File, exaggeration: float, counts: dict[str, int], instances: dict[str, int]
) -> None:
    from misrgraph.io.passes import KIND_NAMES, OrbitPass
    from misrgraph.model.errormodels import AttitudeErrorModel, EphemerisErrorModel

    prov = {k: (v.decode() if isinstance(v, bytes) else str(v)) for k, v in f["provenance"].attrs.items()}
    orbit_pass = OrbitPass.load(prov["pass_file"]) if "pass_file" in prov and Path(prov["pass_file"]).exists() else None
    truth = read_pass_truth(prov["pass_file"]) if orbit_pass is not None else None
    # globe and orbit
    rec.log("world/globe", rr.LineStrips3D(_graticule(), colors=[[90, 90, 90]], radii=2000.0), static=True)
    counts["world/globe"] = 1
    if orbit_pass is not None:
        geo = orbit_pass.geometry(_camera_of(f))
        t = orbit_pass.ephemeris.t
        nav = geo.nav_state(t)
        track = np.einsum("nij,nj->ni", nav.eci_to_ecef, nav.position)
        rec.log("world/orbit", rr.LineStrips3D([track], colors=[[255, 200, 0]], radii=3000.0), static=True)
        counts["world/orbit"] = 1
        tt = np.arange(t[0], t[-1], 30.0)
        for c, name in enumerate(CAMERAS):
            lines = []
            for ti in tt:
                line = (ti - orbit_pass.t0[c, 2]) / orbit_pass.line_time
                g = geo.pixel_to_ground(c, 2, np.full(2, np.floor(line)), np.array([0.0, 1503.0]))
                lines.append(g)
            rec.send_columns(
                f"world/footprints/{name}",
                indexes=[rr.TimeColumn("pass_time", duration=tt)],
                columns=rr.LineStrips3D.columns(strips=lines),
            )
            counts[f"world/footprints/{name}"] = tt.size
    # landmarks
    ecef = read_dataset(f["landmarks"], "ecef", (None, 3))
    cov = read_dataset(f["landmarks"], "covariance", (ecef.shape[0], 3, 3))
    kind = read_dataset(f["landmarks"], "kind", (ecef.shape[0],), dtype=np.int64)
    for k, name in KIND_NAMES.items():
        sel = kind == k
        if not sel.any():
            continue
        rec.log(
            f"world/landmarks/{name}", rr.Points3D(ecef[sel], colors=[KIND_COLORS[name]], radii=1500.0), static=True
        )
        half, quat = ellipsoid_axes(cov[sel], 3.0, exaggeration)
        rec.log(
            f"world/landmarks/{name}/ellipsoids",
            rr.Ellipsoids3D(
                centers=ecef[sel],
                half_sizes=half,
                quaternions=[rr.Quaternion(xyzw=q) for q in quat],
                colors=[KIND_COLORS[name]],
                labels=[f"3 sigma x {exaggeration:g}"] * int(sel.sum()),
            ),
            static=True,
        )
        counts[f"world/landmarks/{name}"] = 1  # one static row holding every landmark of the kind
        counts[f"world/landmarks/{name}/ellipsoids"] = 1
        instances[f"world/landmarks/{name}"] = int(sel.sum())
    if orbit_pass is not None and truth is not None:
        chk = orbit_pass.landmarks.kind == 2
        if chk.any():
            rec.log(
                "world/landmarks/check",
                rr.Points3D(truth.landmark_ecef[chk], colors=[KIND_COLORS["check"]], radii=1500.0),
                static=True,
            )
            counts["world/landmarks/check"] = 1
            instances["world/landmarks/check"] = int(chk.sum())
    # attitude with sigma bands
    att_t, att_k, att_c = [], [], []
    for i, a in enumerate(ANGLES):
        g = f[f"attitude_error/{a}"]
        att_t.append(read_dataset(g, "knot_times", (None,)))
        att_k.append(read_dataset(g, "knots", (None, 2)))
        att_c.append(read_dataset(g, "joint_covariance", (None, None)))
    model = AttitudeErrorModel(att_t, att_k)
    t0, t1 = att_t[0][0], att_t[0][-1]
    t = np.arange(t0, t1, 4.096)
    est = model.evaluate(t)
    for i, a in enumerate(ANGLES):
        idx, w = model.bracket(i, t)
        # sigma of a linear combination of the two bracketing knots' (value, rate)
        c = att_c[i]
        rows = np.stack([2 * idx, 2 * idx + 1, 2 * idx + 2, 2 * idx + 3], 1)
        sub = c[rows[:, :, None], rows[:, None, :]]
        sig = np.sqrt(np.einsum("ni,nij,nj->n", w, sub, w))
        base = f"attitude/{a}"
        _log_series(rec, rr, f"{base}/estimate", t, est[:, i] / ARCSEC)
        _log_series(rec, rr, f"{base}/upper", t, (est[:, i] + sig) / ARCSEC)
        _log_series(rec, rr, f"{base}/lower", t, (est[:, i] - sig) / ARCSEC)
        _log_series(rec, rr, f"{base}/knots", att_t[i], att_k[i][:, 0] / ARCSEC)
        for s in ("estimate", "upper", "lower"):
            counts[f"{base}/{s}"] = t.size
        counts[f"{base}/knots"] = att_t[i].size
        removed = read_dataset(f[f"attitude_error/{a}"], "removed_knots", (None,), dtype=np.int64)
        if removed.size:
            times = t0 + removed * _grid_spacing(att_t[i], removed)
            _log_series(rec, rr, f"{base}/removed_knots", times, np.zeros(times.size))
            counts[f"{base}/removed_knots"] = int(times.size)
        if orbit_pass is not None and truth is not None:
            _log_series(rec, rr, f"{base}/truth", t, truth.attitude_error.evaluate(t)[:, i] / ARCSEC)
            counts[f"{base}/truth"] = t.size
    # ephemeris
    eg = f["ephemeris_error"]
    eph = EphemerisErrorModel(read_dataset(eg, "boundaries", (None,)), read_dataset(eg, "params", (None, 6)))
    ecov = read_dataset(eg, "covariance", (eph.n_segments, 6, 6))
    seg, dsn = eph.design(t)
    e = eph.evaluate(t)
    esig = np.sqrt(np.einsum("nij,njk,nlk->nil", dsn, ecov[seg], dsn).diagonal(axis1=1, axis2=2))
    for i, ax in enumerate(("along", "cross", "nadir")):
        base = f"ephemeris/{ax}"
        _log_series(rec, rr, f"{base}/estimate", t, e[:, i])
        _log_series(rec, rr, f"{base}/upper", t, e[:, i] + esig[:, i])
        _log_series(rec, rr, f"{base}/lower", t, e[:, i] - esig[:, i])
        for s in ("estimate", "upper", "lower"):
            counts[f"{base}/{s}"] = t.size
        if orbit_pass is not None and truth is not None:
            _log_series(rec, rr, f"{base}/truth", t, truth.ephemeris_error.evaluate(t)[:, i])
            counts[f"{base}/truth"] = t.size
    # residuals
    res = read_dataset(f["observations"], "residual_px", (None, 2))
    cam = read_dataset(f["observations"], "camera", (res.shape[0],), dtype=np.int64)
    times = orbit_pass.observation_times() if orbit_pass is not None else np.arange(res.shape[0], dtype=float)
    for c, name in enumerate(CAMERAS):
        sel = (cam == c) & np.isfinite(res[:, 0])
        if not sel.any():
            continue
        order = np.argsort(times[sel])
        for j, comp in enumerate(("along", "cross")):
            _log_series(rec, rr, f"residuals/{name}/{comp}", times[sel][order], res[sel][order, j])
            counts[f"residuals/{name}/{comp}"] = int(sel.sum())
        hist, _ = np.histogram(np.hypot(res[sel, 0], res[sel, 1]), bins=np.arange(0, 1.0001, 0.05))
        rec.log(f"residuals/{name}/histogram", rr.BarChart(hist), static=True)
        counts[f"residuals/{name}/histogram"] = 1


def _open_recording(rr: Any, save: str | os.PathLike[str] | None, spawn: bool) -> tuple[Any, Path | None]:
    """A recording stream, saving to a hidden temporary sibling of ``save`` (renamed when the
    recording closes) and/or spawning the viewer."""
    rec = rr.RecordingStream("misrgraph")
    tmp = None
    if save is not None:
        save = Path(save)
        save.parent.mkdir(parents=True, exist_ok=True)
        tmp = save.with_name(f".{save.name}.tmp")
        rec.save(str(tmp))
    if spawn:
        rec.spawn(connect=save is None)
    return rec, tmp


def _close_recording(
    rr: Any, rec: Any, bp: Any, notebook: bool, tmp: Path | None, save: str | os.PathLike[str] | None
) -> None:
    """Send the blueprint, flush, show inline or disconnect, and put the ``.rrd`` in place."""
    rec.send_blueprint(bp)
    rec.flush()
    if notebook:
        rr.notebook_show(recording=rec, blueprint=bp, width=1000, height=600)
    else:
        rec.disconnect()
    if tmp is not None:
        os.replace(tmp, Path(str(save)))


def _view_campaign(
    rr: Any, rrb: Any, out: Path, save: str | os.PathLike[str] | None, spawn: bool, notebook: bool
) -> dict[str, Any]:
    """A campaign directory over years (its ``summary.json``'s ``years``): the entities
    ``years/...`` of the module docstring."""
    import json

    f = out / "summary.json"
    try:
        summary = json.loads(f.read_text())
    except OSError:
        raise FileFormatError(f, "cannot read: not a campaign directory (misrgraph campaign --out)") from None
    except ValueError as exc:
        raise FileFormatError(f, f"not JSON ({exc})") from None
    years = summary.get("years") if isinstance(summary, dict) else None
    if not years or years.get("status") != "done":
        raise FileFormatError(f, "no campaign over years in it (misrgraph campaign --recalibrate MONTHS)")
    rec, tmp = _open_recording(rr, save, spawn)
    dates = np.array([np.datetime64(w["start"], "ns") for w in years["windows"]])
    counts: dict[str, int] = {}
    for cam in CAMERAS:
        for angle, e in years["series"][cam].items():
            v = np.asarray(e["value_arcsec"], float)
            sd = np.asarray(e["sigma_arcsec"], float)
            for name, y in (("value", v), ("upper", v + sd), ("lower", v - sd)):
                path = f"years/{cam}/{angle}/{name}"
                rec.send_columns(
                    path,
                    indexes=[rr.TimeColumn("date", timestamp=dates)],
                    columns=rr.Scalars.columns(scalars=y),
                )
                counts[path] = int(dates.size)
    for v in years["versions"]:
        rec.set_time("date", timestamp=dates[v["window"]])
        rec.log("years/versions", rr.TextLog(f"{v['id']} from orbit {v['first_orbit']}: {v['reason']}"))
    counts["years/versions"] = len(years["versions"])
    for a in years["alarms"]:
        rec.set_time("date", timestamp=dates[a["window"]])
        rec.log(
            "years/alarms",
            rr.TextLog(
                f"{a['camera']} {a['parameter']} {a['kind']}: {a['statistic']:.2f} > {a['threshold']:.2f}",
                level="WARN",
            ),
        )
    counts["years/alarms"] = len(years["alarms"])
    bp = rrb.Blueprint(
        rrb.Vertical(
            rrb.Grid(*[rrb.TimeSeriesView(origin=f"years/{c}", name=f"{c} (arcsec)") for c in CAMERAS]),
            rrb.Horizontal(
                rrb.TextLogView(origin="years/versions", name="versions"),
                rrb.TextLogView(origin="years/alarms", name="alarms"),
            ),
            row_shares=[4, 1],
        )
    )
    _close_recording(rr, rec, bp, notebook, tmp, save)
    return {"kind": "campaign", "entities": counts, "instances": {}, "rrd": str(save) if save else None}


def _grid_spacing(kept_times: np.ndarray, removed: np.ndarray) -> float:
    """Spacing of the uniform knot grid, recovered from kept knot times and removed indices."""
    n = kept_times.size + removed.size
    return float((kept_times[-1] - kept_times[0]) / max(n - 1, 1))


def _camera_of(f: h5py.File):
    return read_camera_group(f["camera_model"])


def _view_calibration(rec, rr, f: h5py.File, counts: dict[str, int]) -> None:
    g = f["calibration"]
    labels = [x.decode() if isinstance(x, bytes) else str(x) for x in g["labels"][()]]
    x = read_dataset(g, "corrections", (len(labels),))
    cov = read_dataset(g, "covariance", (len(labels), len(labels)))
    corr = read_dataset(g, "correlation", (len(labels), len(labels)))
    sig = np.sqrt(np.diag(cov))
    for name in CAMERAS:
        idx = [i for i, lab in enumerate(labels) if lab.startswith(name + ".") or lab.startswith(name + "/")]
        if not idx:
            continue
        scale = np.array(
            [1 / ARCSEC if lab.split(".")[-1] in ("delta", "beta", "epsilon") else 1.0 for lab in np.array(labels)[idx]]
        )
        rec.log(f"calibration/{name}/corrections", rr.BarChart(x[idx] * scale), static=True)
        rec.log(f"calibration/{name}/sigma", rr.BarChart(sig[idx] * scale), static=True)
        counts[f"calibration/{name}/corrections"] = 1
        counts[f"calibration/{name}/sigma"] = 1
    rec.log("calibration/correlation", rr.Tensor(corr, dim_names=["parameter", "parameter"]), static=True)
    rec.log("calibration/labels", rr.TextDocument("\n".join(labels)), static=True)
    counts["calibration/correlation"] = 1


def _view_imagery(rec, rr, path: Path, counts: dict[str, int], max_gcps: int = 5) -> None:
    """The GCP windows of a pass (up to ``max_gcps`` GCPs) per camera, as images in window pixels,
    with the matched (red) and, for simulated passes, true (green) positions, one time step per GCP;
    in the tie points' band (red) when the imagery holds several."""
    from misrgraph.io.imagery import has_matched, read_imagery, read_matched
    from misrgraph.io.passes import KIND_GCP, OrbitPass
    from misrgraph.io.truth import read_pass_truth

    im = read_imagery(path)
    p = OrbitPass.load(path)
    truth = read_pass_truth(path)
    geo = truth.geometry(p) if truth is not None else None
    matched = read_matched(path) if has_matched(path) else None
    rows = list(dict.fromkeys(int(r) for r in im.gcp.landmark))[:max_gcps]
    for n, row in enumerate(rows):
        rec.set_time("gcp", sequence=n)
        for k in np.flatnonzero((im.gcp.landmark == row) & (im.gcp.band == im.band)):  # one band: the tie points
            cam = CAMERAS[int(im.gcp.camera[k])]
            base = f"imagery/{cam}"
            rec.log(f"{base}/window", rr.Image(im.gcp.pixels[k].astype(np.float32)))
            counts["image windows"] = counts.get("image windows", 0) + 1
            if matched is not None:
                mo = matched.observations
                gi = int(p.landmarks.gcp_index[row])
                lm_rows = np.flatnonzero((matched.landmarks.gcp_index == gi) & (matched.landmarks.kind == KIND_GCP))
                sel = np.isin(mo.landmark, lm_rows) & (mo.camera == int(im.gcp.camera[k])) & (mo.band == im.band)
                if sel.any():
                    rec.log(
                        f"{base}/matched",
                        rr.Points2D(
                            np.stack([mo.sample[sel] - im.gcp.sample0[k], mo.line[sel] - im.gcp.line0[k]], 1),
                            colors=[255, 0, 0],
                            radii=1.0,
                        ),
                    )
            if geo is not None:
                ip = geo.ground_to_pixel(
                    int(im.gcp.camera[k]), int(im.gcp.band[k]), truth.landmark_ecef[row][None], continuous=True
                )
                if ip.visible[0]:
                    rec.log(
                        f"{base}/truth",
                        rr.Points2D(
                            [[ip.sample[0] - im.gcp.sample0[k], ip.line[0] - im.gcp.line0[k]]],
                            colors=[0, 255, 0],
                            radii=1.0,
                        ),
                    )


def _view_roi(rec, rr, path: Path, counts: dict[str, int], step: int = 2) -> None:
    """Reference Orbit Imagery: per camera and block (one time step per block), the mosaic (every
    ``step``-th pixel, counts) and its per-pixel source pass (annotated), on the block's SOM grid
    (rows = lines along the path, columns = samples); points terrain hides from the camera in
    every pass have no source (0, unlabelled) and are logged as ``obscured`` where a block has any."""
    from misrgraph.io.roi import read_roi

    roi = read_roi(path)
    # the pass names of the source maps: an annotation context applies to its entity's descendants
    rec.log("roi", rr.AnnotationContext([(i + 1, pid) for i, pid in enumerate(roi.pass_ids)]), static=True)
    for k, block in enumerate(roi.blocks):
        rec.set_time("block", sequence=int(block))
        for c, cam in enumerate(roi.cameras):
            rec.log(f"roi/{cam}/image", rr.Image(roi.pixels[c, k, ::step, ::step].astype(np.float32)))
            rec.log(f"roi/{cam}/source", rr.SegmentationImage((roi.source[c, k, ::step, ::step] + 1).astype(np.uint8)))
            if roi.obscured[c, k].any():
                rec.log(
                    f"roi/{cam}/obscured", rr.SegmentationImage(roi.obscured[c, k, ::step, ::step].astype(np.uint8))
                )
            counts["ROI block images"] = counts.get("ROI block images", 0) + 1


def _view_pp(rec, rr, path: Path, counts: dict[str, int]) -> None:
    """Projection Parameters: per camera and block (one time step per block), the horizontal 1-sigma
    (m) as a heat map on the block's 1.1 km grid (NaN: not imaged), and its line/sample 1-sigma."""
    from misrgraph.io.products import read_pp

    pp = read_pp(path)
    for k, block in enumerate(pp.blocks):
        rec.set_time("block", sequence=int(block))
        for c, cam in enumerate(pp.cameras):
            sig = pp.sigma_m[c, k].astype(np.float32)
            rec.log(f"pp/{cam}/sigma_m", rr.Tensor(np.nan_to_num(sig, nan=0.0), dim_names=["line", "sample"]))
            fin = np.isfinite(sig)
            if fin.any():
                rec.log(f"pp/{cam}/sigma_m_median", rr.Scalars(float(np.median(sig[fin]))))
            counts["PP sigma maps"] = counts.get("PP sigma maps", 0) + 1


def run_view(
    result: str | os.PathLike[str],
    save: str | os.PathLike[str] | None = None,
    spawn: bool = False,
    exaggeration: float = DEFAULT_EXAGGERATION,
    notebook: bool = False,
) -> dict[str, Any]:
    """Log a result file to rerun; save a ``.rrd``, spawn the viewer and/or show it inline in a
    Jupyter notebook (``notebook=True``). Returns the logged entities."""
    rr = require_extra("rerun", "viz", "the rerun viewer")
    import rerun.blueprint as rrb

    if save is None and not spawn and not notebook:
        raise InputError("--save/--spawn", None, "a .rrd file to write, or --spawn to open the viewer")
    if exaggeration <= 0:
        raise InputError("--exaggeration", exaggeration, "a positive factor")
    if Path(result).is_dir():
        return _view_campaign(rr, rrb, Path(result), save, spawn, notebook)
    with open_h5(result) as f:
        kind = str(read_attr(f, "misrgraph_kind"))
        if kind not in (
            "adjustment_result",
            "camera_model",
            "orbit_pass",
            "reference_orbit_imagery",
            "projection_parameters",
        ):
            raise FileFormatError(
                result,
                f"misrgraph_kind {kind!r} cannot be viewed; expected an adjustment result, a "
                "calibrated camera model, a pass file with imagery, Reference Orbit Imagery "
                "or Projection Parameters",
            )
        if kind == "orbit_pass" and "imagery" not in f:
            raise FileFormatError(result, "a pass file without /imagery (simulate with --imagery)")
        if kind == "camera_model" and "calibration" not in f:
            raise FileFormatError(
                result, "a camera model without /calibration (write one with 'misrgraph calibrate --out')"
            )
        rec, tmp = _open_recording(rr, save, spawn)
        counts: dict[str, int] = {}
        instances: dict[str, int] = {}
        if kind == "adjustment_result":
            _view_adjustment(rec, rr, f, exaggeration, counts, instances)
            bp = rrb.Blueprint(
                rrb.Horizontal(
                    rrb.Spatial3DView(origin="world", name="orbit, footprints, landmarks"),
                    rrb.Vertical(
                        *[rrb.TimeSeriesView(origin=f"attitude/{a}", name=f"{a} error (arcsec)") for a in ANGLES],
                        rrb.TimeSeriesView(origin="ephemeris", name="ephemeris error (m)"),
                    ),
                    rrb.Vertical(
                        rrb.TimeSeriesView(origin="residuals", name="residuals (px)"),
                        rrb.BarChartView(origin="residuals/An/histogram", name="An residual histogram"),
                    ),
                )
            )
        elif kind == "reference_orbit_imagery":
            _view_roi(rec, rr, Path(result), counts)
            cams = str(read_attr(f, "cameras")).split(",")
            bp = rrb.Blueprint(rrb.Grid(*[rrb.Spatial2DView(origin=f"roi/{c}", name=f"ROI {c}") for c in cams]))
        elif kind == "projection_parameters":
            _view_pp(rec, rr, Path(result), counts)
            cams = str(read_attr(f, "cameras")).split(",")
            bp = rrb.Blueprint(
                rrb.Grid(*[rrb.TensorView(origin=f"pp/{c}/sigma_m", name=f"PP 1 sigma (m) {c}") for c in cams])
            )
        elif kind == "orbit_pass":
            _view_imagery(rec, rr, Path(result), counts)
            bp = rrb.Blueprint(rrb.Grid(*[rrb.Spatial2DView(origin=f"imagery/{c}", name=c) for c in CAMERAS]))
        else:
            _view_calibration(rec, rr, f, counts)
            bp = rrb.Blueprint(
                rrb.Horizontal(
                    rrb.TensorView(origin="calibration/correlation", name="correlation"),
                    rrb.Vertical(
                        *[
                            rrb.BarChartView(origin=f"calibration/{c}/corrections", name=f"{c} (arcsec)")
                            for c in CAMERAS[:3]
                        ]
                    ),
                )
            )
        _close_recording(rr, rec, bp, notebook, tmp, save)
    return {
        "kind": kind,
        "entities": counts,
        "instances": instances,
        "rrd": str(save) if save else None,
        "exaggeration": exaggeration,
    }
