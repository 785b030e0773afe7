from __future__ import annotations

import numpy as np
import pytest

from misrgraph.sim.terrain import SyntheticTerrain, land_mask
from misrgraph.errors import FileFormatError, InputError
from misrgraph.model.frames import enu_basis
from misrgraph.model.gcp import GcpDatabase
from misrgraph.sim.gcps import generate_gcp_database
from misrgraph.io.truth import read_gcp_truth
from misrgraph.io.gcp import read_gcp_database, save_gcp_database


@pytest.fixture(scope="module")
def db_truth():
    return generate_gcp_database(np.random.default_rng(5), SyntheticTerrain(seed=5), 120, with_chips=True)


@pytest.fixture(scope="module")
def db(db_truth):
    return db_truth[0]


def test_distribution_follows_the_seed(db):
    assert len(db) == 120
    regions, counts = np.unique(db.region, return_counts=True)
    c = dict(zip(regions, counts))
    assert c["USA"] == 60
    assert c["Russia"] + c["Africa"] + c["South America"] == 50
    assert c["Australia/New Zealand"] == 10
    assert land_mask(db.lat, db.lon).mean() > 0.95  # positions carry 30 m errors; truth is on land


def test_database_errors_have_30m_sigma_per_enu_axis(db_truth):
    db, truth = db_truth
    err = db.ecef() - truth
    enu = np.einsum("gji,gj->gi", enu_basis(db.lat, db.lon), err)
    k = enu.size
    chi2 = np.sum((enu / 30.0) ** 2)
    assert abs(chi2 - k) < 4 * np.sqrt(2 * k)
    cov = db.covariance_ecef()
    np.testing.assert_allclose(np.linalg.eigvalsh(cov), 900.0, rtol=1e-9)


def test_round_trip(db_truth, tmp_path):
    db, truth = db_truth
    save_gcp_database(db, tmp_path / "g.h5", truth_ecef=truth)
    back = read_gcp_database(tmp_path / "g.h5")
    np.testing.assert_array_equal(back.lat, db.lat)
    np.testing.assert_array_equal(back.region, db.region)
    assert back.chips.shape == (120, 9, 64, 64)
    np.testing.assert_array_equal(read_gcp_truth(tmp_path / "g.h5"), truth)
    save_gcp_database(db, tmp_path / "real.h5")
    assert read_gcp_truth(tmp_path / "real.h5") is None


def test_validation():
    with pytest.raises(InputError, match="gcp.lat"):
        GcpDatabase(np.arange(1), [95.0], [0.0], [0.0], [30.0], ["x"])
    with pytest.raises(InputError, match="gcp.sigma_m"):
        GcpDatabase(np.arange(1), [5.0], [0.0], [0.0], [0.0], ["x"])
    with pytest.raises(FileFormatError):
        read_gcp_database("/nonexistent.h5")
