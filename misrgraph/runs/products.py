"""``run_products``: the Projection Parameters of one pass of a scenario on its path's SOM grid
(the action behind ``misrgraph products``).

The pass is adjusted on the way (:func:`misrgraph.estimate.adjust.adjust_pass`; the PP need the
joint posterior of the navigation variables, which RESULT.h5 keeps only per angle), then
:func:`misrgraph.products.pp.compute_pp` maps the chosen blocks, and a pass with the simulator's
truth is scored (:func:`misrgraph.evaluate.products.score_pp`). From an incremental update state,
every pass gets its PP from the state's estimate instead.

With ``roi=True`` every pass with whole-swath strips (at least four) is adjusted and mapped, and
the Reference Orbit Imagery of the blocks is built from them (:mod:`misrgraph.products.roi`):
``OUT/ROI_P<path>.h5``, optionally GeoTIFFs and quick-looks, its co-registration measured by
matching on the ROI, and, for simulated passes, its true misregistration
(:func:`misrgraph.evaluate.products.score_roi`).
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np

from misrgraph import __version__
from misrgraph.errors import DegenerateProblemError, FileFormatError, InputError, require_extra
from misrgraph.estimate.adjust import AdjustConfig, AdjustResult
from misrgraph.evaluate.products import score_pp
from misrgraph.io.camera import load_camera_model
from misrgraph.io.dem import read_dem
from misrgraph.io.gcp import read_gcp_database
from misrgraph.io.h5 import atomic_file
from misrgraph.io.imagery import OBSERVATION_SETS
from misrgraph.io.passes import OrbitPass
from misrgraph.io.products import ProjectionParameters, read_pp, save_pp
from misrgraph.io.truth import PassTruth, load_pass_observations, pass_truth_in, read_pass_truth
from misrgraph.misr.som import N_BLOCKS, SomGrid
from misrgraph.model.constants import CAMERAS
from misrgraph.model.frames import ecef_to_geodetic
from misrgraph.products.pp import compute_pp
from misrgraph.products.roi import MIN_ROI_PASSES
from misrgraph.runs.adjust import adjust_observation_set, camera_prior_of
from misrgraph.runs.cgm import resolve_camera_model, resolve_for_passes

__all__ = ["run_products", "parse_blocks", "DEFAULT_BLOCKS", "RoiOptions"]

#: Why the summaries carry ``"roi": null`` without ``--roi``.
ROI_NOTE = (
    "ROI not built: give --roi (it needs at least four passes with whole-swath strips, "
    "simulated with --imagery --roi-blocks A-B)"
)

#: What ``--format`` writes: misrgraph's HDF5 files, or those and MISR's HDF-EOS2 files beside them.
FILE_FORMATS = ("h5", "misr")

#: Blocks mapped when ``--blocks`` is not given: this many, centred on the pass's features.
DEFAULT_BLOCKS = 10


def parse_blocks(text: "str | tuple[int, int]", field: str = "--blocks") -> np.ndarray:
    """``"A-B"`` (inclusive), ``"B"`` or, from Python, a pair ``(A, B)`` -> block numbers; an
    :class:`InputError` names ``field``."""
    if isinstance(text, (tuple, list)) and len(text) == 2 and all(isinstance(v, (int, np.integer)) for v in text):
        text = f"{int(text[0])}-{int(text[1])}"
    if not isinstance(text, str):
        raise InputError(field, text, "a block range 'A-B', one block 'B' or a pair (A, B) of block numbers")
    m = re.fullmatch(r"\s*(\d+)\s*(?:-\s*(\d+)\s*)?", text)
    if not m:
        raise InputError(field, text, "a block range A-B or one block B (1..180)")
    a, b = int(m.group(1)), int(m.group(2) or m.group(1))
    if not 1 <= a <= b <= N_BLOCKS:
        raise InputError(field, text, f"1 <= A <= B <= {N_BLOCKS}")
    return np.arange(a, b + 1)


def _default_blocks(orbit_pass: OrbitPass, res: AdjustResult, grid: SomGrid, n: int) -> np.ndarray:
    """``n`` consecutive blocks around the median block of the pass's adjusted features."""
    pos = np.array([res.values.atVector(int(k)) for k in res.pass_graph.landmark_keys])
    lat, lon, _ = ecef_to_geodetic(pos)
    b, _, _ = grid.latlon_to_bls(lat, lon, strict=False)
    b = b[b > 0]
    if b.size == 0:
        raise DegenerateProblemError(
            f"pass {orbit_pass.pass_id}: none of its features lies on path {grid.path}'s blocks; give --blocks"
        )
    lo = int(np.clip(int(np.median(b)) - n // 2, 1, N_BLOCKS - n + 1))
    return np.arange(lo, lo + n)


def run_products(
    scenario_dir: str | os.PathLike[str],
    out: str | os.PathLike[str],
    blocks: str | tuple[int, int] | None = None,
    pass_file: str | os.PathLike[str] | None = None,
    camera_model: str | os.PathLike[str] | None = None,
    band: str = "red",
    cfg: AdjustConfig = AdjustConfig(),
    progress: Callable[[str, int, int], None] | None = None,
    default_blocks: int = DEFAULT_BLOCKS,
    roi: bool = False,
    roi_options: "RoiOptions | None" = None,
    observations: str = "simulated",
    file_format: str = "h5",
) -> dict[str, Any]:
    """Adjust one pass of ``scenario_dir`` (the only one, or ``pass_file``; for a multi-pass
    scenario the first pass when none is named), compute its PP over ``blocks`` (``"A-B"``;
    default ``default_blocks`` around its features), write ``OUT/PP_<pass id>.h5`` and
    ``OUT/products.json``, and return the summary (with ``pp_error_m`` when the pass has truth).

    ``scenario_dir`` may instead be an incremental ``misrgraph update`` state (it holds
    ``state.json``): every pass of the state (or the one in ``pass_file``, by its pass id) gets its
    PP from the state's current estimate and iSAM2's joint marginals, without re-adjusting; the
    summary then lists them under ``"passes"`` (:func:`_run_products_state`).

    ``roi``: build the Reference Orbit Imagery of the blocks (default: those the strips were
    rendered for) from every pass with strips (:func:`_run_products_roi`; from a state, its
    passes with the state's estimate, the SOM DEM by default beside the state's DEM); the summary
    adds ``"roi"`` (files, clearest pass and share obscured by terrain per block),
    ``"roi_coregistration_px"`` (per camera, the worst over the blocks and over the two kinds,
    against An and across passes, of the block's misregistration measured by matching on the ROI
    beyond matching noise, all pairs of a kind pooled), ``"roi_coregistration"`` (per camera and
    kind, that worst block's statistics, with its interval and worst single pair),
    ``"roi_coregistration_by_block"`` (``{block: {camera: {kind: px}}}``),
    ``"roi_coregistration_unmeasured"`` (``{camera: [blocks]}`` where no pair had 3 matches, also
    in ``"notes"``) and, for simulated passes, ``"roi_truth"`` (the true
    misregistration of the points the ROI keeps) and ``"roi_truth_obscured"`` (per camera, the
    points the terrain mask flags against those the truth hides: ``points``, ``flagged``,
    ``hidden``, ``missed``, ``false``) and ``"roi_truth_by_block"`` (the truth per block).

    ``observations``: the set a scenario's passes are adjusted with (``"simulated"``, their own;
    ``"matched"``, what ``misrgraph match`` measured); a state adjusts its own set.

    ``file_format``: ``"h5"`` (misrgraph's HDF5 files) or ``"misr"`` (those, and beside them in
    ``OUT/misr/`` MISR's HDF-EOS2 files, one per camera: PP and, with ``roi``, ROI; see
    :mod:`misrgraph.io.misrfiles`); the summary then lists them under ``"misr_files"``
    (``{"pp": {pass_id: {camera: path}}, "roi": {camera: path}}``)."""
    if file_format not in FILE_FORMATS:
        raise InputError("--format", file_format, FILE_FORMATS)
    if file_format == "misr":
        require_extra("pyhdf", "misr", "--format misr")
    summary = _run_products_h5(
        scenario_dir,
        out,
        blocks,
        pass_file,
        camera_model,
        band,
        cfg,
        progress,
        default_blocks,
        roi,
        roi_options,
        observations,
    )
    if file_format == "misr":
        summary["misr_files"] = export_misr(summary, _out_dir(out) / "misr")
        with atomic_file(_out_dir(out) / "products.json") as fh:
            fh.write(json.dumps(summary, indent=2))
    return summary


def export_misr(summary: dict[str, Any], out_dir: Path) -> dict[str, Any]:
    """Write MISR HDF-EOS2 files of the PP and ROI files a products summary lists, into
    ``out_dir``; return ``{"pp": {pass_id: {camera: path}}, "roi": {camera: path}}``."""
    from misrgraph.io.misrfiles import misr_file_name, orbit_of_pass_id, write_pp_misr, write_roi_misr

    rows = summary.get("passes") or [summary]
    pps = [read_pp(f) for f in ((row.get("files") or {}).get("pp") for row in rows) if f]
    # MISR names a PP file by path, orbit and camera: two passes of one orbit would collide
    names: dict[str, str] = {}
    for pp in pps:
        name = misr_file_name("PP", pp.path, orbit_of_pass_id(pp.pass_id), pp.cameras[0])
        if name in names:
            raise InputError("pass ids", (names[name], pp.pass_id), "passes of different orbits (MISR's file names)")
        names[name] = pp.pass_id
    pp_files = {pp.pass_id: {c: str(p) for c, p in write_pp_misr(pp, out_dir).items()} for pp in pps}
    roi_files: dict[str, str] = {}
    if summary.get("roi"):
        from misrgraph.io.roi import read_roi

        roi_files = {c: str(p) for c, p in write_roi_misr(read_roi(summary["roi"]["file"]), out_dir).items()}
    return {"pp": pp_files, "roi": roi_files}


def _run_products_h5(
    scenario_dir: str | os.PathLike[str],
    out: str | os.PathLike[str],
    blocks: str | tuple[int, int] | None = None,
    pass_file: str | os.PathLike[str] | None = None,
    camera_model: str | os.PathLike[str] | None = None,
    band: str = "red",
    cfg: AdjustConfig = AdjustConfig(),
    progress: Callable[[str, int, int], None] | None = None,
    default_blocks: int = DEFAULT_BLOCKS,
    roi: bool = False,
    roi_options: "RoiOptions | None" = None,
    observations: str = "simulated",
) -> dict[str, Any]:
    """:func:`run_products` in misrgraph's HDF5 files only."""
    t_start = time.perf_counter()
    d = Path(scenario_dir)
    roi_options = (roi_options or RoiOptions()) if roi else None
    if roi and pass_file is not None:
        raise InputError(
            "--pass", str(pass_file), "no --pass with --roi (the ROI is made of all the passes with strips)"
        )
    if observations not in OBSERVATION_SETS:
        raise InputError("--observations", observations, OBSERVATION_SETS)
    if (d / "state.json").is_file():
        return _run_products_state(d, out, blocks, pass_file, band, progress, default_blocks, t_start, roi_options)
    if not d.is_dir():
        raise InputError("SCENARIO_DIR", str(d), "a directory written by 'misrgraph simulate'")
    if roi:
        return _run_products_roi(d, out, blocks, camera_model, band, cfg, progress, roi_options, t_start, observations)
    if pass_file is None:
        passes = sorted((d / "passes").glob("*.h5"))
        if not passes:
            raise FileFormatError(d / "passes", "no pass files (*.h5)")
        pass_file = passes[0]
    orbit_pass = load_pass_observations(pass_file, observations)[0]
    grid = SomGrid(int(orbit_pass.path), 1100)
    cam_path, cgm_version = resolve_camera_model(
        Path(camera_model) if camera_model else d / "camera_model.h5", orbit_pass.orbit
    )
    camera = load_camera_model(cam_path).at_temperature(orbit_pass.temperature_c)
    out_dir = _out_dir(out)
    if progress:
        progress("adjusting the pass", 0, 1)
    t0 = time.perf_counter()
    res = adjust_observation_set(
        orbit_pass,
        pass_file,
        camera,
        read_dem(d / "dem.h5"),
        read_gcp_database(d / "gcp.h5"),
        cfg,
        observations,
        camera_prior_of(cam_path, cfg),
    )
    t_adjust = time.perf_counter() - t0
    chosen = parse_blocks(blocks) if blocks else _default_blocks(orbit_pass, res, grid, default_blocks)
    provenance = {
        "scenario": str(d),
        "pass_file": str(pass_file),
        "camera_model": str(cam_path),
        **({"cgm_version": cgm_version["id"]} if cgm_version else {}),
        "software": f"misrgraph {__version__}",
        "solver_status": res.status,
        "observation_set": observations,
    }
    row, t_pp, _ = _pass_pp(
        orbit_pass, res, grid.path, chosen, band, out_dir, provenance, read_pass_truth(pass_file), camera, progress
    )
    summary: dict[str, Any] = {
        "path": grid.path,
        "band": band,
        "blocks": [int(chosen.min()), int(chosen.max())],
        **row,
        "roi": None,
        "notes": [ROI_NOTE],
    }
    summary["seconds"] = {"adjust": t_adjust, "pp": t_pp, "total": time.perf_counter() - t_start}
    with atomic_file(out_dir / "products.json") as fh:
        fh.write(json.dumps(summary, indent=2))
    return summary


def _out_dir(out: str | os.PathLike[str]) -> Path:
    """``--out`` as a directory (created when the first PP is written); an existing file there
    is refused."""
    out_dir = Path(out)
    if out_dir.exists() and not out_dir.is_dir():
        raise InputError("--out", str(out_dir), "a directory (created if missing)")
    return out_dir


def _pass_pp(
    orbit_pass: OrbitPass,
    res: AdjustResult,
    path: int,
    chosen: np.ndarray,
    band: str,
    out_dir: Path,
    provenance: dict[str, Any],
    truth: PassTruth | None,
    camera: Any,
    progress: Callable[[str, int, int], None] | None,
    cameras: tuple[str, ...] = CAMERAS,
) -> tuple[dict[str, Any], float, ProjectionParameters]:
    """Compute and write ``OUT/PP_<pass id>.h5`` of one adjusted pass; its summary row
    ``{"pass_id", "files", coverage..., "pp_error_m"?, "seconds_scoring"?}`` (scored against
    ``truth``, the pass file's, when it has one), the seconds the PP took and the PP."""
    t0 = time.perf_counter()
    pp = compute_pp(orbit_pass, res, path, chosen, band=band, progress=progress, cameras=cameras)
    t_pp = time.perf_counter() - t0
    pp.provenance = provenance
    out_dir.mkdir(parents=True, exist_ok=True)
    pp_file = out_dir / f"PP_{orbit_pass.pass_id}.h5"
    save_pp(pp, pp_file)
    row: dict[str, Any] = {"pass_id": orbit_pass.pass_id, "files": {"pp": str(pp_file)}, **pp.coverage()}
    if truth is not None:
        t0 = time.perf_counter()
        row.update(score_pp(pp, orbit_pass, truth, supplied_camera=camera))
        row["seconds_scoring"] = time.perf_counter() - t0
    return row, t_pp, pp


def _run_products_state(
    d: Path,
    out: str | os.PathLike[str],
    blocks: str | None,
    pass_file: str | os.PathLike[str] | None,
    band: str,
    progress: Callable[[str, int, int], None] | None,
    default_blocks: int,
    t_start: float,
    roi_options: "RoiOptions | None" = None,
) -> dict[str, Any]:
    """PP of the passes of an update state from its current estimate (see :func:`run_products`):
    ``{"path", "state", "band", "blocks", "passes": [{"pass_id", "files", coverage..., "pp_error_m"?,
    "seconds"}], "seconds"}``; ``OUT/PP_<pass id>.h5`` per pass and ``OUT/products.json``."""
    from misrgraph.runs.update import restore_state

    out_dir = _out_dir(out)
    t0 = time.perf_counter()
    solver, camera, files = restore_state(d)
    t_restore = time.perf_counter() - t0
    ids = [p.pass_id for p in solver.passes]
    if not ids:
        raise DegenerateProblemError(f"state {d} holds no passes yet; add some with 'misrgraph update'")
    chosen_idx = list(range(len(ids)))
    if pass_file is not None:
        want = OrbitPass.load(pass_file).pass_id
        if want not in ids:
            raise InputError("--pass", str(pass_file), f"a pass of the state ({', '.join(ids)})")
        chosen_idx = [ids.index(want)]
    paths = {int(solver.passes[i].path) for i in chosen_idx}
    if len(paths) != 1:
        raise InputError("state passes", sorted(paths), "passes of one path (PP are per path)")
    grid = SomGrid(paths.pop(), 1100)
    if roi_options is not None:
        adjusted = [(solver.passes[i], solver.pass_result(i), files[i]) for i in chosen_idx]
        # the scenario beside the state's DEM holds its SOM DEM (and, when simulated, its truth)
        dem_file = json.loads((d / "state.json").read_text()).get("dem")
        scenario = Path(dem_file).parent if dem_file else d
        return _roi_stage(
            adjusted,
            grid.path,
            blocks,
            band,
            out_dir,
            d,
            scenario,
            camera,
            progress,
            roi_options,
            {"state": str(d), "restore": t_restore},
            t_start,
        )
    rows = []
    chosen = None
    for n, i in enumerate(chosen_idx):
        t0 = time.perf_counter()
        orbit_pass = solver.passes[i]
        res = solver.pass_result(i)
        if chosen is None:
            chosen = parse_blocks(blocks) if blocks else _default_blocks(orbit_pass, res, grid, default_blocks)
        if progress:
            progress(f"PP of pass {orbit_pass.pass_id} ({n + 1}/{len(chosen_idx)})", n, len(chosen_idx))
        provenance = {
            "state": str(d),
            "pass_file": str(files[i]),
            "camera_model": "the state's",
            "software": f"misrgraph {__version__}",
            "solver_status": "iSAM2 update state",
        }
        row, _, _ = _pass_pp(
            orbit_pass, res, grid.path, chosen, band, out_dir, provenance, read_pass_truth(files[i]), camera, None
        )
        row["seconds"] = time.perf_counter() - t0
        rows.append(row)
    assert chosen is not None
    summary: dict[str, Any] = {
        "path": grid.path,
        "state": str(d),
        "band": band,
        "blocks": [int(chosen.min()), int(chosen.max())],
        "passes": rows,
        "roi": None,
        "notes": [ROI_NOTE],
        "seconds": {"restore": t_restore, "total": time.perf_counter() - t_start},
    }
    with atomic_file(out_dir / "products.json") as fh:
        fh.write(json.dumps(summary, indent=2))
    return summary


# ---------------------------------------------------------------------------- Reference Orbit Imagery
@dataclass(frozen=True)
class RoiOptions:
    """How ``--roi`` runs: the SOM DEM (default ``dem_som.h5`` of the scenario the passes come
    from), GeoTIFF and quick-look exports, the co-registration matches per image pair and
    block (0: not measured), and the points per block the simulator's truth is scored at (0: the
    truth is not scored, nor at the matched points)."""

    som_dem: str | None = None
    geotiff: bool = False
    quicklooks: bool = False
    coregistration_points: int = 64
    truth_points: int = 300

    def __post_init__(self) -> None:
        for name in ("coregistration_points", "truth_points"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 0:
                raise InputError(name, v, "an integer >= 0")


def _run_products_roi(
    d: Path,
    out: str | os.PathLike[str],
    blocks: str | None,
    camera_model: str | os.PathLike[str] | None,
    band: str,
    cfg: AdjustConfig,
    progress: Callable[[str, int, int], None] | None,
    opts: RoiOptions,
    t_start: float,
    observations: str = "simulated",
) -> dict[str, Any]:
    """Adjust every pass of scenario ``d`` that has whole-swath strips (from the ``observations``
    set), then :func:`_roi_stage`."""
    from misrgraph.io.imagery import strip_cameras

    out_dir = _out_dir(out)
    files = [f for f in sorted((d / "passes").glob("*.h5")) if strip_cameras(f)]
    if len(files) < MIN_ROI_PASSES:
        raise InputError(
            "--roi",
            f"{len(files)} passes with whole-swath strips in {d / 'passes'}",
            f"at least {MIN_ROI_PASSES} (simulate a path scenario with --imagery --roi-blocks A-B)",
        )
    passes = [load_pass_observations(f, observations)[0] for f in files]
    cam_path, _ = resolve_for_passes(
        Path(camera_model) if camera_model else d / "camera_model.h5", [int(p.orbit) for p in passes]
    )
    camera_all = load_camera_model(cam_path)
    prior = camera_prior_of(cam_path, cfg)
    dem, gcps = read_dem(d / "dem.h5"), read_gcp_database(d / "gcp.h5")
    adjusted = []
    t0 = time.perf_counter()
    for n, (f, orbit_pass) in enumerate(zip(files, passes)):
        if progress:
            progress(f"adjusting pass {n + 1}/{len(files)}", n, len(files))
        res = adjust_observation_set(
            orbit_pass, f, camera_all.at_temperature(orbit_pass.temperature_c), dem, gcps, cfg, observations, prior
        )
        adjusted.append((orbit_pass, res, f))
    return _roi_stage(
        adjusted,
        int(adjusted[0][0].path),
        blocks,
        band,
        out_dir,
        d,
        d,
        camera_all,
        progress,
        opts,
        {"scenario": str(d), "adjust": time.perf_counter() - t0},
        t_start,
    )


def _roi_stage(
    adjusted: list[tuple[OrbitPass, AdjustResult, Any]],
    path: int,
    blocks: str | None,
    band: str,
    out_dir: Path,
    source: Path,
    scenario: Path,
    camera: Any,
    progress: Callable[[str, int, int], None] | None,
    opts: RoiOptions,
    head: dict[str, Any],
    t_start: float,
) -> dict[str, Any]:
    """PP of every adjusted pass over the ROI's blocks (for the cameras with strips), the ROI built
    and written, its co-registration measured, exports and the summary (``products.json``).
    ``scenario`` is the directory whose ``dem_som.h5`` is the default SOM DEM and whose
    ``scenario.json`` (when simulated) gives the truth's surface. Every pass file is opened (and
    validated) once, for the whole build."""
    from misrgraph.io.imagery import open_strips

    if band != "red":
        raise InputError("--band", band, "red (the strips are rendered in the red band)")
    with contextlib.ExitStack() as stack:
        readers = {str(f): stack.enter_context(open_strips(f)) for _, _, f in adjusted}
        return _roi_build(
            adjusted, readers, path, blocks, band, out_dir, source, scenario, camera, progress, opts, head, t_start
        )


def _roi_build(
    adjusted: list[tuple[OrbitPass, AdjustResult, Any]],
    readers: dict[str, Any],
    path: int,
    blocks: str | None,
    band: str,
    out_dir: Path,
    source: Path,
    scenario: Path,
    camera: Any,
    progress: Callable[[str, int, int], None] | None,
    opts: RoiOptions,
    head: dict[str, Any],
    t_start: float,
) -> dict[str, Any]:
    """:func:`_roi_stage` with every pass file's strips open in ``readers`` (by file name)."""
    from misrgraph.evaluate.products import score_roi, score_roi_matches
    from misrgraph.io.dem import read_som_dem
    from misrgraph.io.roi import export_roi_geotiff, read_roi, roi_writer, write_quicklooks
    from misrgraph.products.roi import (
        RoiPass,
        build_roi,
        coregistration_matches,
        coregistration_stats,
        roi_predicted_coregistration,
    )
    from misrgraph.sim.imagery import FULL_SCALE_DN

    with_strips = [(p, r, f) for p, r, f in adjusted if readers[str(f)].cameras]
    if len(with_strips) < MIN_ROI_PASSES:
        raise InputError(
            "--roi",
            f"{len(with_strips)} passes with whole-swath strips",
            f"at least {MIN_ROI_PASSES} (simulate a path scenario with --imagery --roi-blocks A-B)",
        )
    if len({int(p.path) for p, _, _ in with_strips}) != 1:
        raise InputError("passes", sorted({int(p.path) for p, _, _ in with_strips}), "passes of one path")
    if blocks:
        chosen = parse_blocks(blocks)
    else:
        rendered = {readers[str(f)].blocks for _, _, f in with_strips} - {None}
        if not rendered:
            raise InputError("--blocks", None, "a block range (the strips do not say which blocks they cover)")
        a, b = max(r[0] for r in rendered), min(r[1] for r in rendered)  # type: ignore[index]
        if a > b:
            raise InputError(
                "--blocks", None, f"a block range (the passes' strips cover different blocks: {sorted(rendered)})"
            )
        chosen = np.arange(a, b + 1)
    dem_path = Path(opts.som_dem) if opts.som_dem else scenario / "dem_som.h5"
    if not dem_path.is_file():
        raise InputError(
            "--som-dem", str(dem_path), "a SOM DEM file (dem_som.h5, written by 'misrgraph simulate --roi-blocks')"
        )
    som_dem = read_som_dem(dem_path)
    missing = sorted(set(chosen.tolist()) - set(som_dem.blocks.tolist()))
    if missing or som_dem.path != path:
        raise InputError(
            "--blocks",
            missing or chosen.tolist(),
            f"blocks of the SOM DEM {dem_path} (path {som_dem.path}, "
            f"blocks {som_dem.blocks.min()}-{som_dem.blocks.max()})",
        )
    cameras = tuple(c for c in CAMERAS if any(c in readers[str(f)].cameras for _, _, f in with_strips))
    rows, roi_passes, truths = [], [], []
    t0 = time.perf_counter()
    for n, (orbit_pass, res, f) in enumerate(with_strips):
        if progress:
            progress(f"PP of pass {orbit_pass.pass_id} ({n + 1}/{len(with_strips)})", n, len(with_strips))
        provenance = {
            "source": str(source),
            "pass_file": str(f),
            "software": f"misrgraph {__version__}",
            "solver_status": str(getattr(res, "status", "iSAM2 update state")),
        }
        cam_at = camera.at_temperature(orbit_pass.temperature_c) if hasattr(camera, "at_temperature") else camera
        rd = readers[str(f)]
        truth = pass_truth_in(rd.file)  # from the file the reader validated (not opened again)
        row, _, pp = _pass_pp(orbit_pass, res, path, chosen, band, out_dir, provenance, truth, cam_at, None, cameras)
        rows.append(row)
        roi_passes.append(
            RoiPass(
                orbit_pass.pass_id, pp, lambda cam, lines, rd=rd: rd.strip(cam, lines) if cam in rd.cameras else None
            )
        )
        if truth is not None:
            truths.append((orbit_pass, truth, pp))
    t_pp = time.perf_counter() - t0
    pass_ids = [p.pass_id for p in roi_passes]
    roi_file = out_dir / f"ROI_P{path:03d}.h5"
    coreg: dict[str, dict[str, Any]] = {}
    coreg_by_block: dict[int, dict[str, dict[str, float]]] = {}
    truth_scores: dict[str, dict[str, float]] = {}
    surface = _truth_surface(scenario) if truths else None
    clear: dict[int, dict[str, float]] = {}
    obscured: dict[int, dict[str, float]] = {}
    hidden_counts: dict[str, dict[str, int]] = {}
    truth_by_block: dict[int, dict[str, dict[str, float]]] = {}
    chosen_pass: dict[int, str] = {}
    predicted: dict[int, dict[str, dict[str, float]]] = {}
    t0 = time.perf_counter()
    t_coreg = 0.0
    with roi_writer(roi_file, path, band, cameras, pass_ids, chosen, FULL_SCALE_DN) as writer:
        for blk in build_roi(roi_passes, som_dem, chosen, cameras, full_scale=FULL_SCALE_DN, progress=progress):
            writer.write(blk)
            clear[blk.block] = dict(zip(pass_ids, map(float, blk.clear_fraction)))
            chosen_pass[blk.block] = pass_ids[blk.chosen]
            predicted[blk.block] = roi_predicted_coregistration(
                [rp.pp for rp in roi_passes], blk.block, blk.chosen, cameras, som_dem.sigma_m, som_dem.resolution_m
            )
            obscured[blk.block] = {cam: float(blk.obscured[j].mean()) for j, cam in enumerate(cameras)}
            t1 = time.perf_counter()
            scored = surface is not None and len(truths) == len(roi_passes)
            if opts.coregistration_points:
                matches = coregistration_matches(blk, pass_ids, opts.coregistration_points)
                at_matches = (
                    score_roi_matches(blk.block, truths, som_dem.block(blk.block), cameras, surface, matches)
                    if scored and opts.truth_points
                    else {}
                )
                for cam, kinds in coregistration_stats(matches).items():
                    coreg_by_block.setdefault(blk.block, {})[cam] = {
                        k: float(st["excess_px"]) for k, st in kinds.items()
                    }
                    for kind, st in kinds.items():
                        if kind in at_matches.get(cam, {}):
                            st["truth_at_matches"] = at_matches[cam][kind]
                        best = coreg.setdefault(cam, {}).get(kind)
                        if best is None or st["excess_px"] > best["excess_px"]:
                            coreg[cam][kind] = {**st, "block": blk.block}
            if scored and opts.truth_points:
                sc = score_roi(
                    blk.block,
                    truths,
                    som_dem.block(blk.block),
                    cameras,
                    surface,
                    opts.truth_points,
                    reference=blk.chosen,
                    obscured=blk.hidden,
                )
                for cam, cnt in sc.pop("obscured").items():
                    acc = hidden_counts.setdefault(cam, dict.fromkeys(cnt, 0))
                    for key, v in cnt.items():
                        acc[key] += v
                truth_by_block[blk.block] = sc
                for kind, per_cam in sc.items():
                    for cam, v in per_cam.items():
                        truth_scores.setdefault(kind, {})[cam] = max(truth_scores.get(kind, {}).get(cam, 0.0), v)
            t_coreg += time.perf_counter() - t1
    t_roi = time.perf_counter() - t0 - t_coreg
    roi_summary: dict[str, Any] = {
        "file": str(roi_file),
        "cameras": list(cameras),
        "passes": pass_ids,
        "clear_fraction": clear,
        "chosen_pass": chosen_pass,
        "obscured_fraction": obscured,
    }
    if opts.geotiff or opts.quicklooks:
        r = read_roi(roi_file)
        if opts.geotiff:
            roi_summary["geotiff"] = export_roi_geotiff(r, out_dir)
        if opts.quicklooks:
            roi_summary["quicklooks"] = write_quicklooks(r, out_dir)
    summary: dict[str, Any] = {
        "path": path,
        **{k: v for k, v in head.items() if isinstance(v, str)},
        "band": band,
        "blocks": [int(chosen.min()), int(chosen.max())],
        "passes": rows,
        "roi": roi_summary,
        "roi_coregistration_px": {
            cam: max(float(st["excess_px"]) for st in kinds.values()) for cam, kinds in coreg.items() if kinds
        },
        "roi_coregistration": coreg,
        "roi_coregistration_by_block": coreg_by_block,
        "roi_predicted_px": _worst_block(predicted, cameras),
        "roi_predicted_px_by_block": predicted,
        "notes": [],
    }
    if opts.coregistration_points:
        unmeasured = {cam: [int(b) for b in chosen if not coreg_by_block.get(int(b), {}).get(cam)] for cam in cameras}
        summary["roi_coregistration_unmeasured"] = {cam: bl for cam, bl in unmeasured.items() if bl}
        for cam, bl in summary["roi_coregistration_unmeasured"].items():
            summary["notes"].append(
                f"{cam}: co-registration not measured in blocks {bl} (fewer than 3 matches in "
                f"every pair: sea, cloud or no texture); roi_coregistration_px covers the others"
            )
    if truth_scores:
        summary["roi_truth"] = truth_scores
        summary["roi_truth_obscured"] = hidden_counts
        summary["roi_truth_by_block"] = truth_by_block
    summary["seconds"] = {
        **{k: v for k, v in head.items() if not isinstance(v, str)},
        "pp": t_pp,
        "roi": t_roi,
        "coregistration_and_scoring": t_coreg,
        "total": time.perf_counter() - t_start,
    }
    with atomic_file(out_dir / "products.json") as fh:
        fh.write(json.dumps(summary, indent=2))
    return summary


def _worst_block(
    per_block: dict[int, dict[str, dict[str, float]]], cameras: tuple[str, ...]
) -> dict[str, dict[str, float]]:
    """``{camera: {kind: worst over the blocks}}`` of ``{block: {camera: {kind: px}}}`` (every
    camera of ``cameras``, empty where no block has a figure for it)."""
    worst: dict[str, dict[str, float]] = {cam: {} for cam in cameras}
    for per_cam in per_block.values():
        for cam, kinds in per_cam.items():
            for kind, v in kinds.items():
                worst[cam][kind] = max(v, worst[cam].get(kind, v))
    return worst


def _truth_surface(scenario: Path) -> Callable[[np.ndarray, np.ndarray], np.ndarray] | None:
    """The simulator's true surface (ellipsoidal m) of ``scenario`` (None without ``scenario.json``)."""
    from misrgraph.sim.simulate import scenario_terrain

    meta = scenario / "scenario.json"
    if not meta.is_file():
        return None
    cfg = json.loads(meta.read_text()).get("config", {})
    terrain = scenario_terrain(cfg)
    return lambda la, lo: terrain.height(la, lo)  # the simulator's geoid is zero
