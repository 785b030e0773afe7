from __future__ import annotations

import numpy as np
import pytest

from misrgraph.errors import FileFormatError, InputError
from misrgraph.io.gcp import read_gcp_database, save_gcp_database
from misrgraph.io.truth import read_gcp_truth
from misrgraph.model.frames import enu_basis
from misrgraph.model.gcp import GcpDatabase
from misrgraph.sim.gcps import generate_gcp_database
from misrgraph.sim.terrain import SyntheticTerrain, land_mask


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


def test_scene_catalogue_shares_the_stated_part_of_the_error():
    """The Landsat-scene catalogue: half the variance common per 2 x 2 deg cell. The database
    names the scenes and the shared sigma; the errors of two GCPs of one scene correlate by that
    share, which the own covariance leaves out (closed form: sigma^2 - shared^2 per ENU axis)."""
    dbs, truths = [], []
    for seed in range(40):
        d, t = generate_gcp_database(np.random.default_rng(seed), SyntheticTerrain(seed=5), 120, scene_fraction=0.5)
        dbs.append(d)
        truths.append(t)
    d0 = dbs[0]
    assert d0.scene is not None and d0.scene_sigma_m is not None
    np.testing.assert_allclose(d0.scene_sigma_m, 30.0 * np.sqrt(0.5))
    cell = np.floor(d0.lat / 2.0) * 1000 + np.floor(d0.lon / 2.0)
    for s, rows in d0.scenes().items():  # one scene per 2 x 2 deg cell (positions carry 30 m errors)
        assert np.unique(cell[rows]).size == 1
    # pairs of GCPs of one scene: their east errors correlate by 0.5 over the 40 catalogues
    prod, sq = [], []
    for d, t in zip(dbs, truths):
        enu = np.einsum("gji,gj->gi", enu_basis(d.lat, d.lon), d.ecef() - t)
        for rows in d.scenes().values():
            if rows.size >= 2:
                prod.append(enu[rows[0]] * enu[rows[1]])
        sq.append(enu**2)
    rho = np.mean(prod) / np.mean(sq)
    n = len(prod) * 3
    assert n > 300
    assert (
        abs(rho - 0.5) < 4 * (1 - 0.25) / np.sqrt(n) + 0.05
    )  # 4 standard errors of a correlation (heavy tails: + 0.05)
    own = d0.own_covariance_ecef()
    np.testing.assert_allclose(np.linalg.eigvalsh(own), 450.0, rtol=1e-9)
    np.testing.assert_allclose(
        d0.covariance_ecef() - own, own, atol=1e-9
    )  # fraction 0.5: the shared part equals the own


def test_scene_round_trip_and_validation(tmp_path):
    d, t = generate_gcp_database(np.random.default_rng(3), SyntheticTerrain(seed=5), 120, scene_fraction=0.3)
    save_gcp_database(d, tmp_path / "s.h5", truth_ecef=t)
    back = read_gcp_database(tmp_path / "s.h5")
    np.testing.assert_array_equal(back.scene, d.scene)
    np.testing.assert_array_equal(back.scene_sigma_m, d.scene_sigma_m)
    plain, _ = generate_gcp_database(np.random.default_rng(3), SyntheticTerrain(seed=5), 120)
    save_gcp_database(plain, tmp_path / "p.h5")
    assert read_gcp_database(tmp_path / "p.h5").scene is None and plain.scenes() == {}
    np.testing.assert_allclose(plain.own_covariance_ecef(), plain.covariance_ecef())
    one = dict(
        id=np.arange(2), lat=[5.0, 5.1], lon=[0.0, 0.1], height=[0.0, 0.0], sigma_m=[30.0, 30.0], region=["x", "x"]
    )
    with pytest.raises(InputError, match="scene_sigma_m"):
        GcpDatabase(**one, scene=np.array([0, 0]))
    with pytest.raises(InputError, match=r"scene_sigma_m\[1\]"):
        GcpDatabase(**one, scene=np.array([0, 0]), scene_sigma_m=np.array([20.0, 30.0]))
    with pytest.raises(InputError, match="one value"):
        GcpDatabase(**one, scene=np.array([0, 0]), scene_sigma_m=np.array([20.0, 10.0]))
    with pytest.raises(InputError, match="gcp.scene"):
        GcpDatabase(**one, scene=np.array([0, -2]), scene_sigma_m=np.array([20.0, 20.0]))
    ok = GcpDatabase(**one, scene=np.array([-1, 4]), scene_sigma_m=np.array([99.0, 20.0]))
    assert ok.scene_sigma_m[0] == 0.0 and list(ok.scenes()) == [4]
