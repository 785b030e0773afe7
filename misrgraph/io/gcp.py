"""GCP database files (HDF5 kind ``gcp_database``): the one reader and writer.

Layout: group ``/gcp`` with datasets ``id (G,)``, ``lat, lon (G,)`` deg WGS84, ``height (G,)`` m
ellipsoidal, ``sigma_m (G,)`` or ``(G, 3)`` m (1 sigma on every ENU axis, or per axis E, N, U), ``region (G,)``
strings and optional ``chips (G, 9, 64, 64)`` uint8 (attribute ``cameras``), optional ``scene (G,)`` int (source scene,
-1 none) with ``scene_sigma_m (G,)`` m (the share of sigma common to a scene's GCPs). A simulated database also holds
``/truth/ecef (G, 3)`` m, the true positions, read only by :mod:`misrgraph.io.truth`.
"""

from __future__ import annotations

import os
from typing import Any

import h5py
import numpy as np
from numpy.typing import ArrayLike

from misrgraph.errors import FileFormatError, InputError
from misrgraph.io.h5 import atomic_h5, create_dataset, open_h5, read_dataset, write_dataset
from misrgraph.model.gcp import GcpDatabase

__all__ = ["save_gcp_database", "read_gcp_database", "write_gcp_truth"]


def write_gcp_truth(f: Any, truth_ecef: ArrayLike, n: int) -> None:
    """Write ``/truth/ecef (n, 3)`` (m, ECEF) into an open file."""
    t = np.asarray(truth_ecef, float)
    if t.shape != (n, 3):
        raise InputError("truth_ecef", t.shape, f"shape ({n}, 3)")
    write_dataset(f.create_group("truth"), "ecef", t, units="m", frame="ECEF")


def save_gcp_database(db: GcpDatabase, path: str | os.PathLike[str], truth_ecef: ArrayLike | None = None) -> None:
    """Write a GCP database atomically; ``truth_ecef (G, 3)`` m: the simulator's true positions."""
    with atomic_h5(path, "gcp_database") as f:
        g = f.create_group("gcp")
        write_dataset(g, "id", db.id)
        write_dataset(g, "lat", db.lat, units="deg", datum="WGS84")
        write_dataset(g, "lon", db.lon, units="deg", datum="WGS84")
        write_dataset(g, "height", db.height, units="m", reference="WGS84 ellipsoid")
        write_dataset(
            g,
            "sigma_m",
            db.sigma_m,
            units="m",
            meaning="1 sigma per ENU axis"
            + (" (east, north, up)" if db.sigma_m.ndim == 2 else " (the same on all three)"),
        )
        g.create_dataset("region", data=np.asarray(db.region, dtype=object), dtype=h5py.string_dtype())
        if db.chips is not None:
            create_dataset(g, "chips", db.chips, compression="gzip")
            g["chips"].attrs["cameras"] = "Df,Cf,Bf,Af,An,Aa,Ba,Ca,Da"
        if db.scene is not None and db.scene_sigma_m is not None:
            write_dataset(g, "scene", db.scene, meaning="source scene of each GCP (-1: none)")
            write_dataset(
                g,
                "scene_sigma_m",
                db.scene_sigma_m,
                units="m",
                meaning="1 sigma per ENU axis of the error the GCPs of one scene share (part of sigma_m)",
            )
        if truth_ecef is not None:
            write_gcp_truth(f, truth_ecef, len(db))


def read_gcp_database(path: str | os.PathLike[str]) -> GcpDatabase:
    """Read a GCP database (never its truth), validating every field."""
    with open_h5(path, "gcp_database") as f:
        if "gcp" not in f:
            raise FileFormatError(path, "missing group /gcp")
        g = f["gcp"]
        ids = read_dataset(g, "id", (None,), dtype=np.int64)
        n = ids.size
        region = read_dataset(g, "region", (n,), dtype=None)
        region = np.array([r.decode() if isinstance(r, bytes) else str(r) for r in region])
        chips = read_dataset(g, "chips", (n, 9, None, None), dtype=np.uint8) if "chips" in g else None
        scene = read_dataset(g, "scene", (n,), dtype=np.int64) if "scene" in g else None
        scene_sigma = read_dataset(g, "scene_sigma_m", (n,)) if "scene_sigma_m" in g else None
        return GcpDatabase(
            ids,
            read_dataset(g, "lat", (n,)),
            read_dataset(g, "lon", (n,)),
            read_dataset(g, "height", (n,)),
            read_dataset(g, "sigma_m", (n, 3) if "sigma_m" in g and g["sigma_m"].ndim == 2 else (n,)),
            region,
            chips,
            scene,
            scene_sigma,
        )
