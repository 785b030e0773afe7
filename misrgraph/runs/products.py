"""``run_products``: the Projection Parameters of one pass of a scenario on its path's SOM grid
(the action behind ``misrgraph products``).

The pass is adjusted on the way (:func:`misrgraph.estimate.adjust.adjust_pass`; the PP need the
joint posterior of the navigation variables, which RESULT.h5 keeps only per angle), then
:func:`misrgraph.products.pp.compute_pp` maps the chosen blocks, and a pass with the simulator's
truth is scored (:func:`misrgraph.evaluate.products.score_pp`). From an incremental update state,
every pass gets its PP from the state's estimate instead. Reference Orbit Imagery needs
whole-block imagery, which the simulator does not render yet (:data:`ROI_NOTE`): it is not
produced.
"""

from __future__ import annotations

import json
import os
import re
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np

from misrgraph import __version__
from misrgraph.errors import DegenerateProblemError, FileFormatError, InputError
from misrgraph.estimate.adjust import AdjustConfig, AdjustResult, adjust_pass
from misrgraph.evaluate.products import score_pp
from misrgraph.io.camera import load_camera_model
from misrgraph.io.dem import read_dem
from misrgraph.io.gcp import read_gcp_database
from misrgraph.io.h5 import atomic_file
from misrgraph.io.passes import OrbitPass
from misrgraph.io.products import save_pp
from misrgraph.io.truth import read_pass_truth
from misrgraph.misr.som import N_BLOCKS, SomGrid
from misrgraph.model.frames import ecef_to_geodetic
from misrgraph.products.pp import compute_pp

__all__ = ["run_products", "parse_blocks", "DEFAULT_BLOCKS"]

#: Why the summaries carry ``"roi": null``.
ROI_NOTE = "ROI not produced: the simulator renders image windows around features, not whole blocks"

#: Blocks mapped when ``--blocks`` is not given: this many, centred on the pass's features.
DEFAULT_BLOCKS = 10


def parse_blocks(text: str) -> np.ndarray:
    """``"A-B"`` (inclusive) or ``"B"`` -> block numbers; an :class:`InputError` names ``--blocks``."""
    m = re.fullmatch(r"\s*(\d+)\s*(?:-\s*(\d+)\s*)?", text or "")
    if not m:
        raise InputError("--blocks", text, "a block range A-B or one block B (1..180)")
    a, b = int(m.group(1)), int(m.group(2) or m.group(1))
    if not 1 <= a <= b <= N_BLOCKS:
        raise InputError("--blocks", text, f"1 <= A <= B <= {N_BLOCKS}")
    return np.arange(a, b + 1)


def _default_blocks(orbit_pass: OrbitPass, res: AdjustResult, grid: SomGrid, n: int) -> np.ndarray:
    """``n`` consecutive blocks around the median block of the pass's adjusted features."""
    pos = np.array([res.values.atVector(int(k)) for k in res.pass_graph.landmark_keys])
    lat, lon, _ = ecef_to_geodetic(pos)
    b, _, _ = grid.latlon_to_bls(lat, lon, strict=False)
    b = b[b > 0]
    if b.size == 0:
        raise DegenerateProblemError(f"pass {orbit_pass.pass_id}: none of its features lies on path {grid.path}'s blocks; "
                                     "give --blocks")
    lo = int(np.clip(int(np.median(b)) - n // 2, 1, N_BLOCKS - n + 1))
    return np.arange(lo, lo + n)


def run_products(
    scenario_dir: str | os.PathLike[str],
    out: str | os.PathLike[str],
    blocks: str | None = None,
    pass_file: str | os.PathLike[str] | None = None,
    camera_model: str | os.PathLike[str] | None = None,
    band: str = "red",
    cfg: AdjustConfig = AdjustConfig(),
    progress: Callable[[str, int, int], None] | None = None,
    default_blocks: int = DEFAULT_BLOCKS,
) -> dict[str, Any]:
    """Adjust one pass of ``scenario_dir`` (the only one, or ``pass_file``; for a multi-pass
    scenario the first pass when none is named), compute its PP over ``blocks`` (``"A-B"``;
    default ``default_blocks`` around its features), write ``OUT/PP_<pass id>.h5`` and
    ``OUT/products.json``, and return the summary (with ``pp_error_m`` when the pass has truth).

    ``scenario_dir`` may instead be an incremental ``misrgraph update`` state (it holds
    ``state.json``): every pass of the state (or the one in ``pass_file``, by its pass id) gets its
    PP from the state's current estimate and iSAM2's joint marginals, without re-adjusting; the
    summary then lists them under ``"passes"`` (:func:`_run_products_state`)."""
    t_start = time.perf_counter()
    d = Path(scenario_dir)
    if (d / "state.json").is_file():
        return _run_products_state(d, out, blocks, pass_file, band, progress, default_blocks, t_start)
    if not d.is_dir():
        raise InputError("SCENARIO_DIR", str(d), "a directory written by 'misrgraph simulate'")
    if pass_file is None:
        passes = sorted((d / "passes").glob("*.h5"))
        if not passes:
            raise FileFormatError(d / "passes", "no pass files (*.h5)")
        pass_file = passes[0]
    orbit_pass = OrbitPass.load(pass_file)
    grid = SomGrid(int(orbit_pass.path), 1100)
    cam_path = Path(camera_model) if camera_model else d / "camera_model.h5"
    camera = load_camera_model(cam_path).at_temperature(orbit_pass.temperature_c)
    out_dir = _out_dir(out)
    if progress:
        progress("adjusting the pass", 0, 1)
    t0 = time.perf_counter()
    res = adjust_pass(orbit_pass, camera, read_dem(d / "dem.h5"), read_gcp_database(d / "gcp.h5"), cfg)
    t_adjust = time.perf_counter() - t0
    chosen = parse_blocks(blocks) if blocks else _default_blocks(orbit_pass, res, grid, default_blocks)
    provenance = {"scenario": str(d), "pass_file": str(pass_file), "camera_model": str(cam_path),
                  "software": f"misrgraph {__version__}", "solver_status": res.status}
    row, t_pp = _pass_pp(orbit_pass, res, grid.path, chosen, band, out_dir, provenance, pass_file, camera, progress)
    summary: dict[str, Any] = {"path": grid.path, "band": band, "blocks": [int(chosen.min()), int(chosen.max())], **row,
                               "roi": None, "notes": [ROI_NOTE]}
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


def _pass_pp(orbit_pass: OrbitPass, res: AdjustResult, path: int, chosen: np.ndarray, band: str, out_dir: Path,
             provenance: dict[str, Any], pass_file: str | os.PathLike[str], camera: Any,
             progress: Callable[[str, int, int], None] | None) -> tuple[dict[str, Any], float]:
    """Compute and write ``OUT/PP_<pass id>.h5`` of one adjusted pass; its summary row
    ``{"pass_id", "files", coverage..., "pp_error_m"?, "seconds_scoring"?}`` (scored when the pass
    file holds truth) and the seconds the PP took."""
    t0 = time.perf_counter()
    pp = compute_pp(orbit_pass, res, path, chosen, band=band, progress=progress)
    t_pp = time.perf_counter() - t0
    pp.provenance = provenance
    out_dir.mkdir(parents=True, exist_ok=True)
    pp_file = out_dir / f"PP_{orbit_pass.pass_id}.h5"
    save_pp(pp, pp_file)
    row: dict[str, Any] = {"pass_id": orbit_pass.pass_id, "files": {"pp": str(pp_file)}, **pp.coverage()}
    truth = read_pass_truth(pass_file)
    if truth is not None:
        t0 = time.perf_counter()
        row.update(score_pp(pp, orbit_pass, truth, supplied_camera=camera))
        row["seconds_scoring"] = time.perf_counter() - t0
    return row, t_pp


def _run_products_state(d: Path, out: str | os.PathLike[str], blocks: str | None, pass_file: str | os.PathLike[str] | None,
                        band: str, progress: Callable[[str, int, int], None] | None, default_blocks: int,
                        t_start: float) -> dict[str, Any]:
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
        provenance = {"state": str(d), "pass_file": str(files[i]), "camera_model": "the state's",
                      "software": f"misrgraph {__version__}", "solver_status": "iSAM2 update state"}
        row, _ = _pass_pp(orbit_pass, res, grid.path, chosen, band, out_dir, provenance, files[i], camera, None)
        row["seconds"] = time.perf_counter() - t0
        rows.append(row)
    assert chosen is not None
    summary: dict[str, Any] = {"path": grid.path, "state": str(d), "band": band, "blocks": [int(chosen.min()), int(chosen.max())],
                               "passes": rows, "roi": None, "notes": [ROI_NOTE],
                               "seconds": {"restore": t_restore, "total": time.perf_counter() - t_start}}
    with atomic_file(out_dir / "products.json") as fh:
        fh.write(json.dumps(summary, indent=2))
    return summary
