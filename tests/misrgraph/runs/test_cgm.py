"""Camera-model versions by orbit range: the store's index written field by field, the version a
pass's orbit picks, the propagated pointing sigma against sampling, a diff against a change
made by hand, and ``adjust`` with a store equal to ``adjust`` with the version's file."""

from __future__ import annotations

import json
import math

import h5py
import numpy as np
import pytest
from typer.testing import CliRunner

from misrgraph.commands.cli import app
from misrgraph.errors import FileFormatError, InputError
from misrgraph.io.camera import write_camera_group
from misrgraph.io.cgm import INDEX_NAME, open_store, version_for_orbit
from misrgraph.io.h5 import atomic_h5, write_dataset
from misrgraph.model.constants import CAMERAS
from misrgraph.model.nominal import nominal_camera_model
from misrgraph.runs.cgm import run_cgm_add, run_cgm_diff, run_cgm_list, run_cgm_show

ARCSEC = math.pi / 180 / 3600


def _model_file(path, shift_arcsec=None, sigma_arcsec=None):
    """The nominal model, ``shift_arcsec = {(camera, param): arcsec}`` added, with a diagonal
    calibration covariance of ``sigma_arcsec`` on every camera's delta, beta, epsilon."""
    m = nominal_camera_model()
    for (cam, p), v in (shift_arcsec or {}).items():
        m.add_correction(p, CAMERAS.index(cam), None, v * ARCSEC)
    with atomic_h5(path, "camera_model") as f:
        write_camera_group(f.create_group("camera_model"), m)
        if sigma_arcsec is not None:
            labels = [f"{c}.{p}" for c in CAMERAS for p in ("delta", "beta", "epsilon")]
            g = f.create_group("calibration")
            g.create_dataset("labels", data=np.array(labels, dtype=object), dtype=h5py.string_dtype())
            write_dataset(g, "covariance", np.eye(len(labels)) * (sigma_arcsec * ARCSEC) ** 2)
    return path


def test_versions_by_orbit_range(tmp_path):
    store = tmp_path / "cgm"
    a = _model_file(tmp_path / "a.h5")
    b = _model_file(tmp_path / "b.h5", {("Da", "delta"): 2.0})
    run_cgm_add(store, a, 1000, reason="launch")
    res = run_cgm_add(store, b, 5000, reason="monitor: Da delta")
    doc = json.loads((store / INDEX_NAME).read_text())
    assert doc["kind"] == "misrgraph-cgm-store" and doc["format"] == 1
    v1, v2 = doc["versions"]
    assert (v1["id"], v1["first_orbit"], v1["last_orbit"], v1["reason"]) == ("v001", 1000, 4999, "launch")
    assert (v2["id"], v2["first_orbit"], v2["last_orbit"]) == ("v002", 5000, None)
    assert (store / v2["file"]).read_bytes() == b.read_bytes()
    assert res["versions"] == run_cgm_list(store)["versions"]
    s = open_store(store)
    assert version_for_orbit(s, 1000)[0].id == "v001" and version_for_orbit(s, 4999)[0].id == "v001"
    assert version_for_orbit(s, 5000)[0].id == "v002" and version_for_orbit(s, 90000)[0].id == "v002"
    with pytest.raises(InputError, match="v001 1000-4999"):
        version_for_orbit(s, 999)
    # a bounded version inside an existing range is refused; one in a gap is not
    with pytest.raises(InputError, match="outside version v002"):
        run_cgm_add(store, a, 6000, 7000)
    with pytest.raises(InputError, match="--to-orbit"):
        run_cgm_add(store, a, 100, 50)
    assert run_cgm_add(store, a, 10, 999)["added"]["id"] == "v003"
    # not a camera model: refused before anything is stored
    bad = tmp_path / "bad.h5"
    bad.write_text("not hdf5")
    with pytest.raises(FileFormatError, match="bad.h5"):
        run_cgm_add(store, bad, 100000)
    assert len(open_store(store).versions) == 3
    # one add at a time: a store whose lock is held refuses another, and is left as it was
    import fcntl

    with open(store / ".lock", "a+") as held:
        fcntl.flock(held.fileno(), fcntl.LOCK_EX)
        with pytest.raises(InputError, match="holds the lock"):
            run_cgm_add(store, a, 200000)
    assert len(open_store(store).versions) == 3
    # a stored file that changed is refused when picked
    (store / v2["file"]).write_bytes(a.read_bytes())
    with pytest.raises(FileFormatError, match="v002"):
        version_for_orbit(open_store(store), 6000)


def test_show_and_diff_against_a_change_made_by_hand(tmp_path):
    store = tmp_path / "cgm"
    sig = 1.5
    run_cgm_add(store, _model_file(tmp_path / "a.h5", sigma_arcsec=sig), 0)
    run_cgm_add(store, _model_file(tmp_path / "b.h5", {("Da", "delta"): 6.0}, sigma_arcsec=sig), 100)
    nominal = nominal_camera_model()
    shown = run_cgm_show(store, orbit=150)
    assert shown["id"] == "v002" and shown["covariance"]
    da = shown["cameras"]["Da"]
    assert da["delta"]["arcsec"] == pytest.approx(nominal.delta[CAMERAS.index("Da")] / ARCSEC + 6.0, abs=1e-9)
    assert da["delta"]["sigma_arcsec"] == pytest.approx(sig)
    # the propagated pointing sigma against sampling: the RMS pointing change of corrections
    # drawn from the covariance (200 draws: within 15 %)
    from misrgraph.estimate.calibrate import pointing_error_px

    rng = np.random.default_rng(4)
    c = CAMERAS.index("Da")
    draws = []
    for _ in range(200):
        m = nominal.copy()
        for p in ("delta", "beta", "epsilon"):
            m.add_correction(p, c, None, rng.normal(0.0, sig * ARCSEC))
        draws.append(pointing_error_px(m, nominal, c) ** 2)
    assert run_cgm_show(store, "v001")["cameras"]["Da"]["sigma_px"] == pytest.approx(
        math.sqrt(np.mean(draws)), rel=0.15
    )
    d = run_cgm_diff(store, "v001", "v002")
    assert d["cameras"]["Da"]["delta"]["arcsec"] == pytest.approx(6.0, abs=1e-9)
    assert d["cameras"]["Da"]["delta"]["z"] == pytest.approx(6.0 / (sig * math.sqrt(2)))
    # unchanged cameras: zero but for arccos rounding (~1e-8 rad, ~1e-4 px)
    assert all(d["cameras"][k]["pointing_px"] < 1e-3 for k in CAMERAS if k != "Da")
    assert d["cameras"]["Da"]["pointing_px"] > 0.1
    assert d["largest"]["camera"] == "Da" and d["largest"]["z"] > 2
    with pytest.raises(InputError, match="VERSION"):
        run_cgm_diff(store, "v001", "v009")
    with pytest.raises(InputError, match="exactly one"):
        run_cgm_show(store)


def test_cgm_cli(tmp_path):
    store = tmp_path / "cgm"
    a = _model_file(tmp_path / "a.h5")
    r = CliRunner().invoke(app, ["cgm", "add", str(store), str(a), "--from-orbit", "7", "--json"])
    assert r.exit_code == 0, r.output
    assert json.loads(r.stdout)["added"]["first_orbit"] == 7
    r = CliRunner().invoke(app, ["cgm", "list", str(store)])
    assert r.exit_code == 0 and "v001" in r.output
    r = CliRunner().invoke(app, ["cgm", "show", str(store), "--orbit", "3"])
    assert r.exit_code == 2 and "orbit" in r.output and "Traceback" not in r.output
    r = CliRunner().invoke(app, ["cgm", "list", str(tmp_path)])
    assert r.exit_code == 2 and "not a CGM store" in r.output


def test_adjust_picks_the_version_valid_for_the_pass_orbit(small_pass_dir, tmp_path):
    from misrgraph.io.passes import OrbitPass
    from misrgraph.runs.adjust import run_adjust

    pass_file = sorted((small_pass_dir / "passes").glob("*.h5"))[0]
    orbit = OrbitPass.load(pass_file).orbit
    store = tmp_path / "cgm"
    # the simulator counts orbits from the scenario's start: this pass's orbit is small
    run_cgm_add(store, _model_file(tmp_path / "later.h5", {("Cf", "beta"): 20.0}), orbit + 1, reason="later")
    run_cgm_add(store, small_pass_dir / "camera_model.h5", orbit, orbit, reason="this pass's")
    by_store = run_adjust(small_pass_dir, camera_model=store)
    by_file = run_adjust(small_pass_dir, camera_model=store / "versions" / "v002.h5")
    assert by_store["camera_model_version"]["id"] == "v002"
    assert by_store["final_cost"] == pytest.approx(by_file["final_cost"], rel=1e-9)
    assert "camera_model_version" not in by_file or by_file["camera_model_version"] is None


def test_an_update_state_keeps_to_its_version(path_dir, tmp_path):
    """A state created with a store adjusts with the version valid for its first passes and
    refuses, before changing anything, a pass whose orbit another version covers."""
    from misrgraph.io.passes import OrbitPass
    from misrgraph.runs.update import load_state, run_update

    files = sorted((path_dir / "passes").glob("*.h5"))[:2]
    o0, o1 = (OrbitPass.load(f).orbit for f in files)
    assert o1 > o0
    store = tmp_path / "cgm"
    run_cgm_add(store, path_dir / "camera_model.h5", o0, reason="first")
    state = tmp_path / "state"
    kw0 = {"gcp_file": path_dir / "gcp.h5", "dem_file": path_dir / "dem.h5"}
    run_update(tmp_path / "early", files[:1], camera_model=store, **kw0)  # v001 open-ended then
    run_cgm_add(store, path_dir / "camera_model.h5", o1, reason="second")  # closes v001 at o1 - 1
    with pytest.raises(InputError, match="version v001"):  # the store's current range, not the one recorded
        run_update(tmp_path / "early", files[1:])
    kw = {"gcp_file": path_dir / "gcp.h5", "dem_file": path_dir / "dem.h5"}
    with pytest.raises(InputError, match="span v001, v002"):
        run_update(state, files, camera_model=store, **kw)
    run_update(state, files[:1], camera_model=store, **kw)
    meta = load_state(state).meta
    assert meta["cgm"]["id"] == "v001" and meta["camera_model"] == str((store / "versions" / "v001.h5").resolve())
    before = (state / "state.json").read_bytes()
    with pytest.raises(InputError, match="version v001"):
        run_update(state, files[1:])
    assert (state / "state.json").read_bytes() == before
