"""``misrgraph info``: validate a misrgraph HDF5 file and summarise what it holds."""

from __future__ import annotations

import os
from typing import Any

import numpy as np

from misrgraph.io.camera import load_camera_model
from misrgraph.io.dem import read_dem
from misrgraph.io.gcp import read_gcp_database
from misrgraph.io.h5 import open_h5, read_attr
from misrgraph.io.truth import has_truth
from misrgraph.model.constants import BANDS

__all__ = ["run_info"]


def run_info(path: str | os.PathLike[str]) -> dict[str, Any]:
    """Kind, format version and counts of a file, after fully loading (validating) it."""
    with open_h5(path) as f:
        kind = str(read_attr(f, "misrgraph_kind"))
        version = int(read_attr(f, "format_version"))
    out: dict[str, Any] = {"file": str(path), "kind": kind, "format_version": version}
    if kind == "orbit_pass":
        from misrgraph.io.passes import KIND_NAMES, OrbitPass

        p = OrbitPass.load(path)
        t0, t1 = p.span
        out.update(
            {
                "pass_id": p.pass_id,
                "path": p.path,
                "orbit": p.orbit,
                "epoch_utc": p.ephemeris.epoch_utc,
                "time_span_s": [t0, t1],
                "duration_s": t1 - t0,
                "ephemeris_samples": int(p.ephemeris.t.size),
                "landmarks": {KIND_NAMES[k]: int(np.sum(p.landmarks.kind == k)) for k in KIND_NAMES},
                "observations": len(p.observations),
                "temperature_c": p.temperature_c,
                "has_truth": has_truth(path, "orbit_pass"),
            }
        )
        from misrgraph.io.imagery import has_imagery, has_matched, read_imagery, read_matched

        if has_imagery(path):
            im = read_imagery(path)
            out["imagery"] = {
                "tie_windows": len(im.tie),
                "tie_window_px": im.tie.size,
                "gcp_windows": len(im.gcp),
                "gcp_window_px": im.gcp.size,
                "gcp_chips": int(np.unique(im.chip_landmark).size),
                "gcp_window_bands": [BANDS[int(b)] for b in np.unique(im.gcp.band)],
                **im.attrs,
            }
            from misrgraph.io.imagery import strip_cameras

            if strip_cameras(path):
                out["imagery"]["strip_cameras"] = list(strip_cameras(path))
        if has_matched(path):
            m = read_matched(path)
            out["matched"] = {"landmarks": len(m.landmarks), "observations": len(m.observations)}
    elif kind == "camera_model":
        from misrgraph.model.camera import CameraModel

        lm = load_camera_model(path)
        m = lm if isinstance(lm, CameraModel) else lm.models[0]
        out.update({"cameras": 9, "bands": 4, "temperature_c": m.temperature_c, "provenance": m.provenance})
        if not isinstance(lm, CameraModel):
            out.update(
                {"temperature_table_c": [float(t) for t in lm.temperatures_c], "valid_range_c": list(lm.valid_range_c)}
            )
    elif kind == "gcp_database":
        g = read_gcp_database(path)
        regions, counts = np.unique(g.region, return_counts=True)
        out.update(
            {
                "gcps": len(g),
                "regions": {str(r): int(c) for r, c in zip(regions, counts)},
                "has_chips": g.chips is not None,
                "has_truth": has_truth(path, "gcp_database"),
                "sigma_m_median": (
                    np.median(g.sigma_m, axis=0).tolist() if g.sigma_m.ndim == 2 else float(np.median(g.sigma_m))
                )
                if len(g)
                else None,
            }
        )
    elif kind == "dem":
        d = read_dem(path)
        out.update(
            {
                "tiles": int(d.lat0.size),
                "postings_per_side": d.size,
                "posting_arcsec": d.posting_deg * 3600,
                "dted1_fraction": float(np.mean(d.quality == 1)) if d.lat0.size else 0.0,
                "height_reference": _dem_height_reference(path),
            }
        )
    elif kind == "projection_parameters":
        from misrgraph.io.products import read_pp

        pp = read_pp(path)
        out.update(
            {
                "path": pp.path,
                "resolution_m": pp.resolution_m,
                "band": pp.band,
                "pass_id": pp.pass_id,
                "blocks": [int(pp.blocks.min()), int(pp.blocks.max())],
                "n_blocks": int(pp.blocks.size),
                **pp.coverage(),
            }
        )
    elif kind == "som_dem":
        from misrgraph.io.dem import read_som_dem

        sd = read_som_dem(path)
        out.update(
            {
                "path": sd.path,
                "resolution_m": sd.resolution_m,
                "blocks": [int(sd.blocks.min()), int(sd.blocks.max())],
                "sigma_m": sd.sigma_m,
                "source": sd.source,
                "height_reference": "WGS84 ellipsoid",
            }
        )
    elif kind == "reference_orbit_imagery":
        from misrgraph.io.roi import read_roi

        r = read_roi(path)
        out.update(
            {
                "path": r.path,
                "band": r.band,
                "cameras": list(r.cameras),
                "passes": list(r.pass_ids),
                "blocks": [int(r.blocks.min()), int(r.blocks.max())],
                "chosen_pass": {int(b): r.pass_ids[int(r.chosen[k])] for k, b in enumerate(r.blocks)},
                "fraction_imaged": {c: float(np.mean(r.source[i] >= 0)) for i, c in enumerate(r.cameras)},
                "fraction_cloudy": {
                    c: float(np.mean(r.cloudy[i][r.source[i] >= 0])) if np.any(r.source[i] >= 0) else None
                    for i, c in enumerate(r.cameras)
                },
                "fraction_obscured": {c: float(np.mean(r.obscured[i])) for i, c in enumerate(r.cameras)},
            }
        )
    else:
        from misrgraph.io.results import summarise_result_file

        out.update(summarise_result_file(path, kind))
    return out


def _dem_height_reference(path: str | os.PathLike[str]) -> str:
    with open_h5(path, "dem") as f:
        ref = f["tiles"].attrs.get("height_reference", "mean sea level")
    return ref.decode() if isinstance(ref, bytes) else str(ref)
