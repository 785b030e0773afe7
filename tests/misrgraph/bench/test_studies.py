"""``misrgraph bench``: the commands run and their figures are consistent (never timed assertions)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from misrgraph.errors import InputError


@pytest.fixture(scope="module")
def bench_dir(tmp_path_factory):
    return tmp_path_factory.mktemp("bench")


def test_interval_from_the_run_to_run_scatter():
    """Student-t interval, closed form: values 1, 2, 3 -> mean 2, half width t(0.975, 2) / sqrt(3)."""
    from scipy import stats

    from misrgraph.bench.studies import _interval

    iv = _interval([1.0, 2.0, 3.0])
    half = stats.t.ppf(0.975, 2) * 1.0 / np.sqrt(3)
    assert iv["mean"] == 2.0 and iv["ci95"] == pytest.approx([2.0 - half, 2.0 + half], rel=1e-12)


def test_rms_of_runs_is_unbiased_where_the_mean_ratio_is_not():
    """Closed form on 1, 2, 3 (RMS sqrt(14/3), the t interval of the squares square-rooted); and on
    4000 honest runs with k = 3 effective degrees of freedom each (ratio sqrt(chi2_3 / 3)), the
    RMS of the ratios is 1 within 4 standard errors of the mean square (sqrt(2/3) / sqrt(4000))
    while their mean is E[chi_3] / sqrt(3) = 0.921 (closed form)."""
    from scipy import stats
    from scipy.special import gamma

    from misrgraph.bench.studies import _rms_interval

    iv = _rms_interval([1.0, 2.0, 3.0])
    sq = np.array([1.0, 4.0, 9.0])
    half = stats.t.ppf(0.975, 2) * sq.std(ddof=1) / np.sqrt(3)
    assert iv["rms"] == pytest.approx(np.sqrt(14 / 3), rel=1e-12)
    assert iv["ci95"] == pytest.approx([np.sqrt(max(14 / 3 - half, 0.0)), np.sqrt(14 / 3 + half)], rel=1e-12)
    r = np.sqrt(np.random.default_rng(8).chisquare(3, 4000) / 3)
    se = np.sqrt(2 / 3) / np.sqrt(4000)
    assert abs(_rms_interval(list(r))["rms"] ** 2 - 1.0) < 4 * se
    mean_ratio = np.sqrt(2 / 3) * gamma(2.0) / gamma(1.5)
    assert mean_ratio == pytest.approx(0.921, abs=1e-3)
    assert abs(r.mean() - mean_ratio) < 4 * r.std() / np.sqrt(r.size)


def test_bench_nees_per_class_at_reduced_size(bench_dir):
    """Two reduced adjustment runs: every class (knots, ephemeris, camera, landmarks, state and its
    two parts) is
    reported with its chi-square band and an interval from the runs; an unknown size is refused."""
    from misrgraph.bench.studies import run_bench_nees

    r = run_bench_nees("adjust", runs=2, seed=1000, workdir=bench_dir)
    assert r["truth"] == "model" and r["adjust_overrides"] == {"attitude_jitter_arcsec": 0.0}
    assert set(r["summary"]) >= {
        "knots",
        "ephemeris",
        "landmarks",
        "landmarks_common",
        "landmarks_within",
        "state",
        "state_landmarks_given_rest",
        "state_rest",
        "checkpoint_rms_over_predicted",
        "checkpoint_rms_m",
    }
    # the landmarks' two parts are averaged over the same landmarks as the landmarks' NEES
    assert r["summary"]["landmarks_within"]["dof"] <= r["summary"]["landmarks"]["dof"]
    # the whole state's chi-square is the sum of its two parts, run by run and pooled
    sm = r["summary"]
    assert sm["state_landmarks_given_rest"]["dof"] + sm["state_rest"]["dof"] == sm["state"]["dof"]
    assert (
        sm["state_landmarks_given_rest"]["nees_per_dim"] * sm["state_landmarks_given_rest"]["dof"]
        + sm["state_rest"]["nees_per_dim"] * sm["state_rest"]["dof"]
    ) == pytest.approx(sm["state"]["nees_per_dim"] * sm["state"]["dof"])
    for k, v in r["summary"].items():
        lo, hi = v["per_run"]["ci95"]
        assert lo <= v["per_run"]["mean"] <= hi, k
        assert ("band" in v) == (k not in ("checkpoint_rms_over_predicted", "checkpoint_rms_m")), k
        if "band" in v:
            assert v["band"][0] < 1 < v["band"][1], k
        assert v["per_run"]["mean"] == pytest.approx(np.mean([p[k] for p in r["per_run"]]))
    rr = r["summary"]["checkpoint_rms_over_predicted"]["rms_of_runs"]
    assert rr["rms"] == pytest.approx(np.sqrt(np.mean([p["checkpoint_rms_over_predicted"] ** 2 for p in r["per_run"]])))
    # per camera: the RMS over the runs of each run's actual / predicted, from the runs' own figures
    by_cam = r["summary"]["checkpoint_rms_over_predicted"]["by_camera"]
    assert set(by_cam) == set(r["per_run"][0]["checkpoint_by_camera"])
    for c, v in by_cam.items():
        ratios = [
            p["checkpoint_by_camera"][c]["rms_m"] / p["checkpoint_by_camera"][c]["predicted_rms_m"]
            for p in r["per_run"]
            if c in p["checkpoint_by_camera"]
        ]
        assert v["runs"] == len(ratios) and v["rms"] == pytest.approx(np.sqrt(np.mean(np.square(ratios))))
    # the CLI prints them (the same passes, reused from the workdir)
    from typer.testing import CliRunner

    from misrgraph.commands.cli import app

    out = CliRunner().invoke(
        app, ["bench", "nees", "--study", "adjust", "--runs", "2", "--seed", "1000", "--workdir", str(bench_dir)]
    )
    assert out.exit_code == 0, out.output
    for c, v in by_cam.items():
        assert f"{c}: RMS of {v['runs']} runs {v['rms']:.3f}" in out.output
    with pytest.raises(InputError, match="size"):
        run_bench_nees("adjust", runs=1, size="huge", workdir=bench_dir)


def test_bench_nees_pool_of_parts_equals_the_whole(bench_dir, tmp_path):
    """Two one-run studies pooled (``pool_bench_nees``, ``bench nees-pool``) give the two-run
    study's figures; unlike studies and a seed counted twice are refused by name."""
    import json

    from typer.testing import CliRunner

    from misrgraph.bench.studies import pool_bench_nees, run_bench_nees
    from misrgraph.commands.cli import app

    whole = run_bench_nees("adjust", runs=2, seed=1000, workdir=bench_dir)
    parts = [run_bench_nees("adjust", runs=1, seed=s, workdir=bench_dir) for s in (1001, 1000)]
    pooled = pool_bench_nees(parts)
    assert pooled["runs"] == 2 and pooled["pooled_from"] == 2
    assert set(pooled["summary"]) == set(whole["summary"])
    for k, v in whole["summary"].items():
        p = pooled["summary"][k]
        for f in ("nees_per_dim", "dof"):
            if f in v:
                assert p[f] == pytest.approx(v[f], rel=1e-12), (k, f)
        if "band" in v:
            assert p["band"] == pytest.approx(v["band"]) and p["inside"] == v["inside"]
        assert p["per_run"]["mean"] == pytest.approx(v["per_run"]["mean"])
        assert p["per_run"]["ci95"] == pytest.approx(v["per_run"]["ci95"])
    cp, cw = pooled["summary"]["checkpoint_rms_over_predicted"], whole["summary"]["checkpoint_rms_over_predicted"]
    assert cp["rms_of_runs"]["rms"] == pytest.approx(cw["rms_of_runs"]["rms"])
    assert {c: v["rms"] for c, v in cp["by_camera"].items()} == pytest.approx(
        {c: v["rms"] for c, v in cw["by_camera"].items()}
    )
    # the CLI reads bench nees --json files
    files = []
    for n, r in enumerate(parts):
        files.append(tmp_path / f"part{n}.json")
        files[-1].write_text(json.dumps(r))
    out = CliRunner().invoke(app, ["bench", "nees-pool", *map(str, files)])
    assert out.exit_code == 0, out.output
    assert "pooled 2 runs from 2 results" in out.output
    assert f"NEES/dim {whole['summary']['landmarks']['nees_per_dim']:.3f}" in out.output
    with pytest.raises(InputError, match="seeds"):
        pool_bench_nees([parts[0], whole])
    with pytest.raises(InputError, match="truth"):
        pool_bench_nees([parts[0], {**parts[1], "truth": "independent"}])
    with pytest.raises(InputError, match=r"results\[1\]\.per_run"):
        pool_bench_nees([parts[0], {**parts[1], "per_run": [{"landmarks": 1.0}]}])
    bad = tmp_path / "bad.json"
    bad.write_text("[1, 2]")
    out = CliRunner().invoke(app, ["bench", "nees-pool", str(bad)])
    assert out.exit_code == 2 and "expected a bench nees --json output" in out.output


def test_bench_pp_at_reduced_size(bench_dir):
    """The PP honesty study on two reduced passes (the bench runs more): the cameras that see the
    block scored, intervals from the runs, the PP better than the supplied navigation in each."""
    from misrgraph.bench.studies import run_bench_pp

    res = run_bench_pp(runs=2, seed=5000, workdir=bench_dir, blocks_per_pass=1)
    per_cam = res["summary"]["per_camera"]
    assert len(res["per_run"]) == 2
    # a 10-minute pass's Df view runs ~7 minutes ahead and may miss the block; the others see it
    assert set(per_cam) >= {"Cf", "Bf", "Af", "An", "Aa", "Ba", "Ca", "Da"}
    for cam, v in per_cam.items():
        assert v["passes"] == sum(cam in r["nees"] for r in res["per_run"])
        if v["passes"] == 2:
            lo, hi = v["rms_over_predicted"]["ci95"]
            assert lo <= v["rms_over_predicted"]["mean"] <= hi
        assert v["improvement_over_supplied"]["mean"] > 2.0, cam
    # two passes cannot pin honesty down, but a sigma off by a factor of three would show
    assert 1 / 3 < res["summary"]["rms_over_predicted_all_cameras"]["mean"] < 3

    # the same passes scored on a chosen block, per block: one block's figures are its cameras'
    b = int(res["per_run"][0]["blocks"][0])
    blk = run_bench_pp(runs=2, seed=5000, workdir=bench_dir, block_range=f"{b}-{b}")
    per_block = blk["summary"]["per_block"]
    assert blk["block_range"] == f"{b}-{b}" and set(per_block) == set(blk["summary"]["per_camera"])
    for cam, v in per_block.items():
        assert list(v) == [b]
        one = v[b]
        assert one["passes"] == blk["summary"]["per_camera"][cam]["passes"]
        assert one["rms_over_predicted"] == pytest.approx(one["error_px_rms"] / one["predicted_px_rms"])
        assert 1 / 3 < one["rms_over_predicted"] < 3, cam
        # a camera's PP ratio in metres and in pixels agree for one block (same points, one scale)
        ratio_m = np.sqrt(
            np.mean([r["rms_over_predicted"][cam] ** 2 for r in blk["per_run"] if cam in r["rms_over_predicted"]])
        )
        assert one["rms_over_predicted_rms_of_runs"]["rms"] == pytest.approx(ratio_m, rel=0.25), cam


def test_bench_pp_refuses_a_bad_block_range(tmp_path):
    """From the API and the CLI: the option and the value named, nothing simulated."""
    from typer.testing import CliRunner

    from misrgraph.bench.studies import run_bench_pp
    from misrgraph.commands.cli import app

    with pytest.raises(InputError, match="--block-range"):
        run_bench_pp(runs=2, workdir=tmp_path, block_range="71-66")
    assert list(tmp_path.iterdir()) == []  # refused before any pass was simulated
    out = CliRunner().invoke(app, ["bench", "pp", "--runs", "2", "--workdir", str(tmp_path), "--block-range", "71-66"])
    assert out.exit_code != 0 and "--block-range" in out.output and "71-66" in out.output
    assert list(tmp_path.iterdir()) == []


def test_bench_scaling_times_outside_tracemalloc_and_measures_memory_inside(tmp_path, monkeypatch):
    """``tracemalloc`` slows the Python parts about twofold: each size is solved once timed, with
    tracing off, and once traced for the memory peak (the same problem, the same iterations)."""
    import tracemalloc

    import misrgraph.bench.studies as st

    calls: list[tuple[int, bool]] = []
    real = st.solve

    def spy(problem, params):
        res = real(problem, params)
        calls.append((res.iterations, tracemalloc.is_tracing()))
        return res

    monkeypatch.setattr(st, "solve", spy)
    res = st.run_bench_scaling((30, 60), seed=3, workdir=tmp_path, duration_s=300.0)
    assert [r["tie_points"] for r in res["rows"]] == [30, 60]
    assert [traced for _, traced in calls] == [False, False, True, False, True]  # warm-up, then timed + traced per size
    assert calls[1][0] == calls[2][0] and calls[3][0] == calls[4][0]
    for r in res["rows"]:
        assert r["seconds"] > 0 and r["peak_python_mb"] > 0 and r["iterations"] >= 1
        assert r["seconds_per_iteration"] == pytest.approx(r["seconds"] / r["iterations"])
    assert res["rows"][1]["observations"] > res["rows"][0]["observations"]
    assert np.isfinite(res["exponent_total_vs_tie_points"])


def _fake_bench_nees(effects):
    """A stand-in for run_bench_nees: per seed a shared scatter plus, per source switched off, its
    effect (so a row's per-seed difference from the base is known exactly)."""
    from misrgraph.sim.simulate import INDEPENDENT_SOURCES

    def fake(study, runs, seed, workdir, size, truth, overrides):
        per_run = []
        for s in range(seed, seed + runs):
            scatter = np.sin(s)  # the same on every row: cancels in a paired difference
            shift = sum(effects[k] for k, v in overrides.items() if v == INDEPENDENT_SOURCES[k])
            per_run.append(
                {
                    "seed": s,
                    "knots": 1.0 + scatter,
                    "landmarks": 1.0 + scatter + shift,
                    "camera": 1.0,
                    "checkpoint_rms_over_predicted": 1.0 + 0.1 * scatter + shift,
                    "checkpoint_rms_m": 30.0,
                }
            )
        summary = {
            k: {"per_run": {"mean": float(np.mean([r[k] for r in per_run])), "ci95": [0.0, 2.0]}}
            for k in ("knots", "landmarks", "camera", "checkpoint_rms_over_predicted", "checkpoint_rms_m")
        }
        summary["checkpoint_rms_over_predicted"]["rms_of_runs"] = {"rms": 1.0, "ci95": [0.9, 1.1]}
        return {"summary": summary, "per_run": per_run}

    return fake


def test_bench_sources_compares_each_row_with_its_base_seed_by_seed(monkeypatch):
    """Both modes' rows, their paired flags (PAIRED_SOURCES) and the per-seed differences from
    the base row: with a shared per-seed scatter the difference is exactly the source's effect,
    with an interval of zero width; the check points' ratio is compared as its square."""
    import misrgraph.bench.studies as studies
    from misrgraph.sim.simulate import INDEPENDENT_SOURCES, PAIRED_SOURCES

    effects = {k: 0.01 * (i + 1) for i, k in enumerate(INDEPENDENT_SOURCES)}
    monkeypatch.setattr(studies, "run_bench_nees", _fake_bench_nees(effects))
    res = studies.run_bench_sources(runs=5, seed=100, mode="without")
    assert res["base"] == "all" and list(res["rows"]) == ["all"] + [f"without {k}" for k in INDEPENDENT_SOURCES]
    assert "difference" not in res["rows"]["all"]
    for k, eff in effects.items():
        row = res["rows"][f"without {k}"]
        assert row["paired"] == (k in PAIRED_SOURCES)
        d = row["difference"]["landmarks"]
        assert d["runs"] == 5 and d["mean"] == pytest.approx(eff, abs=1e-12)
        assert d["ci95"] == pytest.approx([eff, eff], abs=1e-9)
        assert row["difference"]["knots"]["mean"] == pytest.approx(0.0, abs=1e-12)
        seeds = np.arange(100, 105)
        sq = np.mean((1 + 0.1 * np.sin(seeds) + eff) ** 2 - (1 + 0.1 * np.sin(seeds)) ** 2)
        assert row["difference"]["checkpoint_rms_over_predicted_squared"]["mean"] == pytest.approx(sq, rel=1e-12)
    res = studies.run_bench_sources(runs=5, seed=100, mode="alone")
    assert res["base"] == "none" and list(res["rows"]) == ["none", *INDEPENDENT_SOURCES, "all"]
    total = sum(effects.values())
    for k, eff in effects.items():  # "none" has every effect; switching k on removes its own
        assert res["rows"][k]["difference"]["landmarks"]["mean"] == pytest.approx(-eff, abs=1e-12)
    assert res["rows"]["all"]["difference"]["landmarks"]["mean"] == pytest.approx(-total, abs=1e-12)
    assert not res["rows"]["all"]["paired"]
    with pytest.raises(InputError, match="mode"):
        studies.run_bench_sources(runs=5, mode="both")
    # the CLI: the table with the paired differences, and a refusal that names the option
    from rich.console import Console
    from typer.testing import CliRunner

    import misrgraph.commands.bench as bench_commands
    from misrgraph.commands.cli import app

    # the table's width, not the CI terminal's
    monkeypatch.setattr(bench_commands, "console", Console(width=300))
    out = CliRunner().invoke(app, ["bench", "sources", "--runs", "3", "--mode", "without"])
    assert out.exit_code == 0, out.output
    for k, eff in effects.items():
        line = next(ln for ln in out.output.splitlines() if f"without {k} " in ln)
        assert f"{eff:+.3f}" in line and (" yes " if k in PAIRED_SOURCES else " no ") in line
    out = CliRunner().invoke(app, ["bench", "sources", "--runs", "3", "--mode", "without", "--json"])
    assert out.exit_code == 0, out.output
    rows = json.loads(out.stdout[out.stdout.index("{") :])["rows"]
    assert {k: rows[f"without {k}"]["paired"] for k in INDEPENDENT_SOURCES} == {
        k: k in PAIRED_SOURCES for k in INDEPENDENT_SOURCES
    }
    assert rows["without mismatch_rate"]["difference"]["landmarks"]["mean"] == pytest.approx(effects["mismatch_rate"])
    out = CliRunner().invoke(app, ["bench", "sources", "--mode", "both"])
    assert out.exit_code == 2 and "--mode" in out.output and "'both'" in out.output
