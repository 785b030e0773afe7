"""``run_match``: measure GCPs and tie points in a scenario's imagery (the action behind
``misrgraph match``; notebooks import it too).

For each pass file with ``/imagery`` (``misrgraph simulate --imagery``): GCP chips and tie points
are matched (:mod:`misrgraph.match.pipeline`) with the supplied navigation, camera model and DEM
(never the truth), and the measured observations written into the pass file's ``/matched`` group
beside the simulated ones (atomically); ``misrgraph adjust --observations matched`` adjusts them.

When the pass carries the simulator's truth, each measurement is scored against it: the true
continuous position of the true ground point (a GCP's true position; for a tie point, the true
ground point of the An pixel that defines it, cast onto the true terrain). The summary's
``error_px`` is per coordinate (line and sample pooled: ``rms``, median ``p50`` and ``p95`` of the
absolute error), ``normalised_error_rms`` the RMS of error / reported sigma over all matches (1 for
an honest sigma and no wrong match), ``wrong_matches`` the matches more than 1 px from the truth
(flagged as blunders in the truth; the adjustment's blunder test must reject them) and
``normalised_error_rms_correct`` the same RMS over the other matches: the sigma's honesty where
the match is right (one 5-px wrong match among 60 moves ``normalised_error_rms`` from 1.2 to 2.3);
the tie points' ``per_camera`` the same per camera, and the GCPs' ``per_band`` per band when they
were matched in several (``simulate --bands red,nir --imagery``). An's tie observations define
their tie points (zero error by construction) and are not scored. ``tie.sigma_scale`` gives each camera's scale of
the matcher's sigma measured from the pass's redundancy (:mod:`misrgraph.match.precision`), and
``gcp.sigma_scale`` the one scale of the pass's GCP sigmas from the same fit (null without tie points).
"""

from __future__ import annotations

import json
import logging
import os
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np

from misrgraph.errors import FileFormatError, InputError
from misrgraph.io.camera import load_camera_model
from misrgraph.io.dem import read_dem
from misrgraph.io.gcp import read_gcp_database
from misrgraph.io.imagery import MatchedSet, has_imagery, read_imagery, write_matched
from misrgraph.io.passes import KIND_CHECK, KIND_GCP, KIND_TIE, Landmarks, Observations, OrbitPass
from misrgraph.io.truth import read_pass_truth
from misrgraph.match.pipeline import (
    AN,
    MatchConfig,
    MatchedObservations,
    gcp_fit_rows,
    match_gcps,
    match_ties,
    scale_gcp_sigmas,
    search_range,
)
from misrgraph.model.constants import BANDS, CAMERAS
from misrgraph.model.dem import Geoid, fit_local_surface

__all__ = ["run_match", "match_pass", "WRONG_MATCH_PX", "TIE_ID_BASE"]

log = logging.getLogger(__name__)
#: a match farther than this from the truth is a wrong match (px, radial)
WRONG_MATCH_PX = 1.0
#: matched tie points get ids TIE_ID_BASE + 20000 * (pass index) + feature index: an interest point
#: is found anew in each pass, so matched tie points are never shared between passes
TIE_ID_BASE = 500_000
_TIES_PER_PASS = 20_000


def _stats(err: np.ndarray, sig: np.ndarray) -> dict[str, Any]:
    """Per-coordinate error statistics of ``err (n, 2)`` px with sigmas ``sig (n,)``."""
    if err.size == 0:
        return {
            "error_px": None,
            "normalised_error_rms": None,
            "wrong_matches": 0,
            "normalised_error_rms_correct": None,
        }
    a = np.abs(err).ravel()
    z = err / sig[:, None]
    wrong = np.hypot(err[:, 0], err[:, 1]) > WRONG_MATCH_PX
    return {
        "error_px": {
            "rms": float(np.sqrt(np.mean(a**2))),
            "p50": float(np.median(a)),
            "p95": float(np.percentile(a, 95)),
        },
        "normalised_error_rms": float(np.sqrt(np.mean(z**2))),
        "wrong_matches": int(np.sum(wrong)),
        "normalised_error_rms_correct": float(np.sqrt(np.mean(z[~wrong] ** 2))) if (~wrong).any() else None,
    }


def _per_band(err: np.ndarray, sig: np.ndarray, band: np.ndarray) -> dict[str, Any]:
    """:func:`_stats` per band of ``band (n,)`` (with the band's match count), or ``{}`` when the
    matches are all in one band."""
    bands = np.unique(band)
    if bands.size < 2:
        return {}
    return {BANDS[int(b)]: {"matched": int(np.sum(band == b)), **_stats(err[band == b], sig[band == b])} for b in bands}


def _scenario_surface(directory: Path) -> Callable[[np.ndarray, np.ndarray], np.ndarray] | None:
    """The simulator's true terrain (ellipsoidal m; zero geoid) from scenario.json, or None."""
    meta = directory / "scenario.json"
    if not meta.exists():
        return None
    from misrgraph.sim.simulate import scenario_terrain

    cfg = json.loads(meta.read_text()).get("config", {})
    return scenario_terrain(cfg).height


def match_pass(
    pass_file: Path,
    camera_path: Path,
    gcp_path: Path,
    dem_path: Path,
    pass_index: int,
    cfg: MatchConfig = MatchConfig(),
    true_surface: Callable | None = None,
    progress: Callable[[str], None] | None = None,
    scored: dict[str, list[tuple[np.ndarray, np.ndarray, np.ndarray]]] | None = None,
) -> dict[str, Any]:
    """Match one pass file and write its ``/matched`` group; return its summary. With truth,
    ``scored`` (when given) collects each kind's ``(error (n, 2) px, sigma (n,) px, band (n,))`` for
    pooling over passes."""
    p = OrbitPass.load(pass_file)
    im = read_imagery(pass_file)
    camera = load_camera_model(camera_path).at_temperature(p.temperature_c)
    gcps = read_gcp_database(gcp_path)
    dem = read_dem(dem_path)
    geoid = Geoid("zero")
    supplied = p.geometry(camera)
    band = im.band  # the tie points'; GCPs may be in several bands (each observation carries its own)

    def dem_height(lat: np.ndarray, lon: np.ndarray) -> np.ndarray:
        """Ellipsoidal DEM height (m); NaN outside the DEM (no prediction there)."""
        s = fit_local_surface(dem, lat, lon, "bicubic")
        return np.where(s.valid, s.height, np.nan) + geoid.undulation(lat, lon)

    lm = p.landmarks
    t0 = time.perf_counter()
    g = match_gcps(im, supplied, gcps.ecef(), lambda row: int(lm.gcp_index[row]), cfg)
    t_gcp = time.perf_counter() - t0
    tie_rows = np.unique(im.tie.landmark[lm.kind[im.tie.landmark] == KIND_TIE])
    t0 = time.perf_counter()
    report = (lambda i, n: progress(f"{p.pass_id}: tie point {i}/{n}")) if progress else None
    fit_gcp = None
    if cfg.gcp_sigma_from_redundancy and cfg.shared_attitude_fit and len(g):
        fit_gcp = gcp_fit_rows(g, supplied, gcps.ecef(), lambda row: int(lm.gcp_index[row]), band)
    features, t = match_ties(im, supplied, dem_height, tie_rows, cfg, progress=report, gcp=fit_gcp)
    scale_gcp_sigmas(g, t.precision, cfg)
    t_tie = time.perf_counter() - t0
    if len(features) > _TIES_PER_PASS:
        raise InputError("tie features", len(features), f"at most {_TIES_PER_PASS} per pass")
    # candidates: the conjugates (non-An windows) of the features An sees
    with_an = np.unique(im.tie.landmark[(im.tie.camera == AN) & np.isin(im.tie.landmark, tie_rows)])
    tie_candidates = int(np.sum(np.isin(im.tie.landmark, with_an) & (im.tie.camera != AN)))
    # --- the matched set: GCPs, tie points, and the pass's check points (scoring only, no observations)
    gcp_rows = sorted(set(g.feature))
    chk_rows = np.flatnonzero(lm.kind == KIND_CHECK)
    new_gcp = {r: i for i, r in enumerate(gcp_rows)}
    n_g, n_t = len(gcp_rows), len(features)
    ids = np.concatenate([lm.id[gcp_rows], TIE_ID_BASE + _TIES_PER_PASS * pass_index + np.arange(n_t), lm.id[chk_rows]])
    kinds = np.concatenate([np.full(n_g, KIND_GCP), np.full(n_t, KIND_TIE), np.full(chk_rows.size, KIND_CHECK)])
    gidx = np.concatenate([lm.gcp_index[gcp_rows], -np.ones(n_t, np.int64), -np.ones(chk_rows.size, np.int64)])
    landmarks = Landmarks(ids.astype(np.int64), kinds.astype(np.int64), gidx.astype(np.int64))

    def obs_of(m: MatchedObservations, rows: np.ndarray) -> Observations:
        n = len(m)
        return Observations(
            rows,
            np.array(m.camera, np.int64),
            np.array(m.band, np.int64).reshape(n),
            np.array(m.line),
            np.array(m.sample),
            np.full(n, np.nan),
            np.array(m.sigma_px),
        )

    o_g = obs_of(g, np.array([new_gcp[r] for r in g.feature], np.int64))
    o_t = obs_of(t, n_g + np.array(t.feature, np.int64))
    obs = Observations(*(np.concatenate([getattr(o_g, f), getattr(o_t, f)]) for f in Observations.__dataclass_fields__))
    summary: dict[str, Any] = {
        "pass_id": p.pass_id,
        "search_px": search_range(cfg, im),
        "gcp": {
            "candidates": g.candidates,
            "matched": len(g),
            "seconds": t_gcp,
            "rejected": dict(g.reasons),
            "sigma_scale": t.precision.gcp.as_dict()
            if t.precision is not None and t.precision.gcp is not None
            else None,
        },
        "tie": {
            "candidates": tie_candidates,
            "matched": int(np.sum(np.array(t.camera) != AN)) if len(t) else 0,
            "features": n_t,
            "seconds": t_tie,
            "rejected": dict(t.reasons),
            "sigma_scale": t.precision.as_dict(CAMERAS) if t.precision is not None else None,
            **(
                {"shared_offset": t.precision.shared_offset.as_dict(CAMERAS)}
                if t.precision is not None and t.precision.shared_offset is not None
                else {}
            ),
        },
    }
    truth = read_pass_truth(pass_file)
    tl = tb = None
    if truth is not None and true_surface is not None:
        true_geo = truth.geometry(p)
        tie_truth = (
            true_geo.pixel_to_ground(
                np.full(n_t, AN),
                band,
                [f.line for f in features],
                [f.sample for f in features],
                surface=true_surface,
                exposure=np.full(n_t, np.nan),
            )
            if n_t
            else np.zeros((0, 3))
        )
        tl = np.concatenate([truth.landmark_ecef[gcp_rows].reshape(-1, 3), tie_truth, truth.landmark_ecef[chk_rows]])
        err = np.full((len(obs), 2), np.nan)
        for cam, b in np.unique(np.stack([obs.camera, obs.band], 1), axis=0) if len(obs) else []:
            sel = np.flatnonzero((obs.camera == cam) & (obs.band == b))
            ip = true_geo.ground_to_pixel(int(cam), int(b), tl[obs.landmark[sel]], continuous=True)
            err[sel, 0] = obs.line[sel] - ip.line
            err[sel, 1] = obs.sample[sel] - ip.sample
        err = np.where(np.isfinite(err), err, 99.0)  # a match where the truth is not visible is wrong
        tb = np.hypot(err[:, 0], err[:, 1]) > WRONG_MATCH_PX
        is_g = np.arange(len(obs)) < len(o_g)
        scored_t = ~is_g & (obs.camera != AN)
        summary["gcp"].update(_stats(err[is_g], obs.sigma_px[is_g]))
        per_band = _per_band(err[is_g], obs.sigma_px[is_g], obs.band[is_g])
        if per_band:  # the band-to-band geometry's measurements, band by band
            summary["gcp"]["per_band"] = per_band
        summary["tie"].update(_stats(err[scored_t], obs.sigma_px[scored_t]))
        if scored is not None:
            scored.setdefault("gcp", []).append((err[is_g], obs.sigma_px[is_g], obs.band[is_g]))
            scored.setdefault("tie", []).append((err[scored_t], obs.sigma_px[scored_t], obs.band[scored_t]))
        summary["tie"]["per_camera"] = {
            CAMERAS[c]: {"matched": int(np.sum(sel)), **_stats(err[sel], obs.sigma_px[sel])}
            for c in range(len(CAMERAS))
            if c != AN and np.any(sel := scored_t & (obs.camera == c))
        }
    write_matched(pass_file, MatchedSet(landmarks, obs, tl, tb, summary))
    return summary


def run_match(
    scenario_dir: str | os.PathLike[str],
    cfg: MatchConfig = MatchConfig(),
    pass_file: str | os.PathLike[str] | None = None,
    progress: Callable[[str], None] | None = None,
) -> dict[str, Any]:
    """Match every pass of a scenario that has imagery (or only ``pass_file``); return
    ``{"gcp": {...}, "tie": {...}, "passes": [...]}`` pooled over passes (see the module docstring)."""
    d = Path(scenario_dir)
    if not d.is_dir():
        raise InputError("SCENARIO_DIR", str(d), "a directory written by 'misrgraph simulate --imagery'")
    files = [Path(pass_file)] if pass_file else sorted((d / "passes").glob("*.h5"))
    if not files:
        raise FileFormatError(d / "passes", "no pass files (*.h5)")
    with_imagery = [f for f in files if has_imagery(f)]
    if not with_imagery:
        raise FileFormatError(files[0], "no pass has /imagery: simulate with --imagery")
    true_surface = _scenario_surface(d)
    all_files = sorted((d / "passes").glob("*.h5"))
    passes = []
    scored: dict[str, list[tuple[np.ndarray, np.ndarray, np.ndarray]]] = {}
    for i, f in enumerate(with_imagery):
        idx = all_files.index(f) if f in all_files else 0
        if progress:
            progress(f"matching {f.name} ({i + 1}/{len(with_imagery)})")
        passes.append(
            match_pass(f, d / "camera_model.h5", d / "gcp.h5", d / "dem.h5", idx, cfg, true_surface, progress, scored)
        )
    out: dict[str, Any] = {"passes": passes}
    for kind in ("gcp", "tie"):
        pooled = {
            "candidates": sum(s[kind]["candidates"] for s in passes),
            "matched": sum(s[kind]["matched"] for s in passes),
            "seconds": sum(s[kind]["seconds"] for s in passes),
        }
        if scored.get(kind):  # with truth: the statistics over every pass's matches
            err, sig, band = (np.concatenate([item[i] for item in scored[kind]]) for i in range(3))
            pooled.update(_stats(err.reshape(-1, 2), sig))
            per_band = _per_band(err.reshape(-1, 2), sig, band)
            if per_band:
                pooled["per_band"] = per_band
        out[kind] = pooled
    return out
