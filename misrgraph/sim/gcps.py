"""The simulated GCP database: true positions on the simulated terrain, database positions with
30 m (1 sigma per ENU axis) errors, stand-in image chips."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from misrgraph.errors import InputError
from misrgraph.model.dem import Geoid
from misrgraph.model.frames import ecef_to_geodetic, enu_basis, geodetic_to_ecef
from misrgraph.model.gcp import GCP_REGIONS, GcpDatabase
from misrgraph.sim.terrain import SyntheticTerrain, land_mask

__all__ = ["generate_gcp_database"]

Array = NDArray[np.float64]


def generate_gcp_database(
    rng: np.random.Generator,
    terrain: SyntheticTerrain,
    n_total: int = 120,
    sigma_m: float = 30.0,
    geoid: Geoid | None = None,
    with_chips: bool = False,
    scene_fraction: float | None = None,
    true_over_stated: float = 1.0,
) -> tuple[GcpDatabase, Array]:
    """Draw GCPs on land in the seed's regions: the database and the true positions ``(G, 3)`` m
    ECEF. The catalogue error per ENU axis is N(0, sigma) (``scene_fraction=None``, what the
    database states), or -- a catalogue built from Landsat scenes -- a share ``scene_fraction``
    of the variance common to the GCPs of one 2 x 2 deg cell (the scene's registration error)
    plus Student-t (4 degrees of freedom) per GCP, sigma per axis in total; the database then
    names each GCP's scene and the shared sigma (``scene``, ``scene_sigma_m``), as a catalogue
    that records its source imagery would. ``true_over_stated``: the errors are drawn with that
    many times the sigma the database states (a catalogue that misstates its accuracy)."""
    if n_total < len(GCP_REGIONS):
        raise InputError("n_gcps", n_total, f"at least {len(GCP_REGIONS)}")
    geoid = geoid or Geoid("zero")
    weights = np.array([w for _, w, _ in GCP_REGIONS], float)
    counts = np.floor(weights / weights.sum() * n_total).astype(int)
    counts[0] += n_total - counts.sum()
    lats, lons, regions = [], [], []
    for (name, _, boxes), count in zip(GCP_REGIONS, counts):
        got = 0
        while got < count:
            box = boxes[rng.integers(len(boxes))]
            la = rng.uniform(box[0], box[1], 64)
            lo = rng.uniform(box[2], box[3], 64)
            ok = land_mask(la, lo)
            take = min(count - got, int(ok.sum()))
            lats += la[ok][:take].tolist()
            lons += lo[ok][:take].tolist()
            regions += [name] * take
            got += take
    lat = np.array(lats)
    lon = np.array(lons)
    h = terrain.height(lat, lon) + geoid.undulation(lat, lon)
    truth = geodetic_to_ecef(lat, lon, h)
    sig = np.full(lat.size, sigma_m)
    enu = enu_basis(lat, lon)
    scene_of, scene_sig = None, None
    if scene_fraction is None:
        err = rng.standard_normal((lat.size, 3)) * sigma_m
    else:
        cell = np.floor(lat / 2.0).astype(np.int64) * 1000 + np.floor(lon / 2.0).astype(np.int64)
        _, scene = np.unique(cell, return_inverse=True)
        common = rng.standard_normal((scene.max() + 1, 3))[scene.ravel()]
        own = rng.standard_t(4.0, (lat.size, 3)) / np.sqrt(2.0)  # unit variance
        err = sigma_m * (np.sqrt(scene_fraction) * common + np.sqrt(1.0 - scene_fraction) * own)
        scene_of = scene.ravel().astype(np.int64)
        scene_sig = np.full(lat.size, sigma_m * np.sqrt(scene_fraction))
    measured = truth + np.einsum("gij,gj->gi", enu, err * true_over_stated)
    mlat, mlon, mh = ecef_to_geodetic(measured)
    chips = None
    if with_chips:
        # stand-in chips: textured patterns unique per GCP and camera (no real imagery offline)
        yy, xx = np.mgrid[0:64, 0:64]
        chips = np.empty((lat.size, 9, 64, 64), np.uint8)
        for i in range(lat.size):
            f = rng.uniform(0.05, 0.3, (9, 2))
            ph = rng.uniform(0, 6.3, (9, 1, 1))
            chips[i] = (127 + 100 * np.sin(f[:, 0, None, None] * xx + f[:, 1, None, None] * yy + ph)).astype(np.uint8)
    return GcpDatabase(
        np.arange(lat.size, dtype=np.int64), mlat, mlon, mh, sig, np.array(regions), chips, scene_of, scene_sig
    ), truth
