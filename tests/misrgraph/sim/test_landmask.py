"""The packed, memory-mapped land mask answers exactly as ``global_land_mask`` does."""

from __future__ import annotations

import numpy as np

from misrgraph.sim import landmask


def test_same_answers_as_global_land_mask(tmp_path, monkeypatch):
    monkeypatch.setenv("MISRGRAPH_CACHE", str(tmp_path))
    landmask._mask.cache_clear()
    try:
        rng = np.random.default_rng(0)
        lat = np.concatenate([np.degrees(np.arcsin(rng.uniform(-1, 1, 20000))), [90.0, -90.0, 0.0, 89.999]])
        lon = np.concatenate([rng.uniform(-180, 180, 20000), [0.0, 0.0, -180.0, 179.999]])
        mine = landmask.is_land(lat, lon)
        assert landmask.mask_cache_path().exists()
        from global_land_mask import globe  # the library's own answer (0.9 GB in this process)

        np.testing.assert_array_equal(mine, globe.is_land(lat.copy(), lon.copy()))
        assert 0.2 < mine[:20000].mean() < 0.4  # about 29 % of the Earth's surface is land
        assert mine.reshape(-1)[:10].shape == (10,) and landmask.is_land(lat[:6].reshape(2, 3), lon[:6].reshape(2, 3)).shape == (2, 3)
    finally:
        landmask._mask.cache_clear()


def test_an_unwritable_cache_falls_back_to_the_temporary_directory(tmp_path, monkeypatch):
    import os
    import tempfile

    monkeypatch.setenv("MISRGRAPH_CACHE", "/proc/misrgraph-cannot-write-here")
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    landmask._mask.cache_clear()
    try:
        assert landmask.is_land([48.86, 0.0], [2.35, -30.0]).tolist() == [True, False]  # Paris, mid-Atlantic
        assert list((tmp_path / f"misrgraph-{os.getuid()}").glob("landmask-*.npy"))
    finally:
        landmask._mask.cache_clear()
