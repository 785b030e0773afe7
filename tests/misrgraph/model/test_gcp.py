from __future__ import annotations

import numpy as np
import pytest

from misrgraph.model.dem import SyntheticTerrain, land_mask
from misrgraph.errors import FileFormatError, InputError
from misrgraph.model.frames import enu_basis
from misrgraph.model.gcp import GcpDatabase, generate_gcp_database


@pytest.fixture(scope="module")
def db():
    return generate_gcp_database(np.random.default_rng(5), SyntheticTerrain(seed=5), 120, with_chips=True)


def test_distribution_follows_the_seed(db):
    assert len(db) == 120
    regions, counts = np.unique(db.region, return_counts=True)
    c = dict(zip(regions, counts))
    assert c["USA"] == 60
    assert c["Russia"] + c["Africa"] + c["South America"] == 50
    assert c["Australia/New Zealand"] == 10
    assert land_mask(db.lat, db.lon).mean() > 0.95  # positions carry 30 m errors; truth is on land


def test_database_errors_have_30m_sigma_per_enu_axis(db):
    err = db.ecef() - db.truth_ecef
    enu = np.einsum("gji,gj->gi", enu_basis(db.lat, db.lon), err)
    k = enu.size
    chi2 = np.sum((enu / 30.0) ** 2)
    assert abs(chi2 - k) < 4 * np.sqrt(2 * k)
    cov = db.covariance_ecef()
    np.testing.assert_allclose(np.linalg.eigvalsh(cov), 900.0, rtol=1e-9)


def test_round_trip(db, tmp_path):
    db.save(tmp_path / "g.h5")
    back = GcpDatabase.load(tmp_path / "g.h5")
    np.testing.assert_array_equal(back.lat, db.lat)
    np.testing.assert_array_equal(back.region, db.region)
    assert back.chips.shape == (120, 9, 64, 64)
    np.testing.assert_array_equal(back.truth_ecef, db.truth_ecef)


def test_validation():
    with pytest.raises(InputError, match="gcp.lat"):
        GcpDatabase(np.arange(1), [95.0], [0.0], [0.0], [30.0], ["x"])
    with pytest.raises(InputError, match="gcp.sigma_m"):
        GcpDatabase(np.arange(1), [5.0], [0.0], [0.0], [0.0], ["x"])
    with pytest.raises(FileFormatError):
        GcpDatabase.load("/nonexistent.h5")
