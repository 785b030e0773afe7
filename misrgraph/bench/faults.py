"""Fault injection: SIGKILL at random points of the commands that write files.

Each trial starts a ``misrgraph`` command in a child process, kills it with SIGKILL at a time drawn
uniformly between the interpreter's start-up (``misrgraph --help``, measured) and the end of an
uninterrupted run of the same command, and then inspects what is on
disk: every file misrgraph would read must be the old one or a complete new one (it opens and
passes every integrity check), nothing may be lost, no pass may be in an update state twice, and
a rerun of the same command must complete. Outcomes are counted per command::

    old            the kill came before the commit: the previous output is there, unchanged
    new            the kill came after the commit: the new output is there and complete
    none           there was no previous output and the kill came before the commit
    half_written   a file that fails to open (must be 0)
    lost           the previous output is gone and no new one is there (must be 0)
    counted_twice  a pass twice in an update state (must be 0)
    rerun_failed   the rerun after the kill did not complete (must be 0)
    debris         hidden temporary files or directories left by the killed process (reported;
                   harmless: every reader ignores them, and ``update`` removes its own)

``misrgraph bench kill`` runs the standard study (20 trials per command); the test suite runs the
same code with a few trials.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np

from misrgraph.errors import InputError, MisrGraphError

__all__ = ["KILL_COMMANDS", "run_kill_trials"]

log = logging.getLogger(__name__)

#: The commands the kill study covers.
KILL_COMMANDS = ("simulate", "calibrate", "adjust", "update")

_FAILURES = ("half_written", "lost", "counted_twice", "rerun_failed")


def _cli(*args: str) -> list[str]:
    return [sys.executable, "-m", "misrgraph.commands.cli", *args]


def _run(cmd: list[str], timeout: float = 1800.0) -> float:
    """Run ``cmd`` to completion; its wall time (s). Raises if it fails."""
    t0 = time.perf_counter()
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
    if r.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd[2:])} failed (exit {r.returncode}): {r.stderr.strip()[-500:]}")
    return time.perf_counter() - t0


def _run_and_kill(cmd: list[str], after_s: float, group: bool = False) -> bool:
    """Start ``cmd`` and SIGKILL it after ``after_s`` seconds; True if it was still running.
    ``group``: start it in a new session and kill its whole process group (a command with child
    processes, e.g. ``campaign``'s Dask workers: what a lost job or machine does)."""
    p = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=group)
    try:
        p.wait(timeout=after_s)
        return False
    except subprocess.TimeoutExpired:
        if group:
            os.killpg(p.pid, signal.SIGKILL)
        else:
            p.send_signal(signal.SIGKILL)
        p.wait()
        return True


def _file_sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _complete_h5(path: Path, kind: str | None = None) -> bool:
    from misrgraph.io.h5 import open_h5

    try:
        with open_h5(path, kind):
            return True
    except MisrGraphError:
        return False


def _hidden(directory: Path) -> list[Path]:
    return [p for p in directory.rglob(".*") if p.name != ".lock"] if directory.exists() else []


# ---------------------------------------------------------------------------- per-command checks
class _Target:
    """One command under test: how to run it, snapshot its output and judge the aftermath."""

    name = ""

    def __init__(self, work: Path, inputs: dict[str, Path]) -> None:
        self.work, self.inputs = work, inputs

    def command(self, trial: int) -> list[str]:  # pragma: no cover - abstract
        raise NotImplementedError

    def reset(self, trial: int) -> None:
        """Bring the output to the state a trial starts from (called before each trial)."""

    def snapshot(self) -> Any:  # pragma: no cover - abstract
        raise NotImplementedError

    def judge(self, before: Any, trial: int) -> str:  # pragma: no cover - abstract
        raise NotImplementedError

    def rerun_ok(self, trial: int) -> bool:
        try:
            _run(self.command(trial))
        except (RuntimeError, subprocess.TimeoutExpired) as exc:
            log.warning("rerun failed: %s", exc)
            return False
        return self.judge(None, trial) in ("new",)

    def debris(self) -> list[Path]:
        return _hidden(self.work)


class _FileOutput(_Target):
    """calibrate / adjust: one HDF5 output file (``--out``), alternately absent and present."""

    kind = ""

    @property
    def out(self) -> Path:
        return self.work / "result.h5"

    def reset(self, trial: int) -> None:
        if trial % 2 == 0 and self.out.exists():
            self.out.unlink()  # every other trial starts without a previous output

    def snapshot(self) -> str | None:
        return _file_sha(self.out) if self.out.exists() else None

    def judge(self, before: str | None, trial: int) -> str:
        if not self.out.exists():
            return "none" if before is None else "lost"
        if not _complete_h5(self.out, self.kind):
            return "half_written"
        return "old" if before is not None and _file_sha(self.out) == before else "new"


class _Calibrate(_FileOutput):
    name, kind = "calibrate", "camera_model"

    def command(self, trial: int) -> list[str]:
        return _cli("calibrate", str(self.inputs["month"]), "--out", str(self.out), "--json")


class _Adjust(_FileOutput):
    name, kind = "adjust", "adjustment_result"

    def command(self, trial: int) -> list[str]:
        return _cli("adjust", str(self.inputs["pass"]), "--out", str(self.out), "--json")


class _Simulate(_Target):
    """simulate into a directory that holds the previous scenario on odd trials."""

    name = "simulate"

    @property
    def out(self) -> Path:
        return self.work / "scen"

    def command(self, trial: int) -> list[str]:
        return _cli(
            "simulate",
            "--scenario",
            "pass",
            "--seed",
            str(100 + trial),
            "--tie-points",
            "30",
            "--check-points",
            "5",
            "--duration",
            "300",
            "--out",
            str(self.out),
            "--json",
        )

    def reset(self, trial: int) -> None:
        if trial % 2 == 0 and self.out.exists():
            shutil.rmtree(self.out)

    def _seed(self) -> int | None:
        from misrgraph.sim.simulate import load_scenario

        try:
            sc = load_scenario(self.out)
            for i in range(len(sc.pass_files)):
                sc.load_pass(i)
        except MisrGraphError:
            return None
        return int(sc.config["config"]["seed"])

    def snapshot(self) -> int | None:
        return self._seed() if self.out.exists() else None

    def judge(self, before: int | None, trial: int) -> str:
        if not self.out.exists() or not any(self.out.iterdir()):
            return "none" if before is None else "lost"
        seed = self._seed()
        if seed is None:
            return "half_written"
        return "new" if seed == 100 + trial else ("old" if seed == before else "half_written")

    def debris(self) -> list[Path]:
        return [p for p in self.work.iterdir() if p.name.startswith(".")] + _hidden(self.out)


class _Update(_Target):
    """update: a state holding pass 0 gets pass 1 added (each trial starts from a fresh copy)."""

    name = "update"

    @property
    def state(self) -> Path:
        return self.work / "state"

    def command(self, trial: int) -> list[str]:
        return _cli("update", str(self.state), str(self.inputs["path_passes"][1]), "--json")

    def reset(self, trial: int) -> None:
        if self.state.exists():
            shutil.rmtree(self.state)
        shutil.copytree(self.inputs["base_state"], self.state)

    def snapshot(self) -> list[str]:
        return list(json.loads((self.state / "state.json").read_text())["passes"])

    def _ids(self) -> list[str] | None:
        from misrgraph.runs.update import _checked_file, load_state

        try:
            st = load_state(self.state)
            if st is None:
                return None
            for e in [*st.meta["passes"], *([st.meta["estimate"]] if st.meta["estimate"] else [])]:
                if not _complete_h5(_checked_file(self.state, e)):
                    return None
        except MisrGraphError:
            return None
        return st.pass_ids

    def judge(self, before: list[dict[str, Any]] | None, trial: int) -> str:
        if not (self.state / "state.json").exists():
            return "lost"
        ids = self._ids()
        if ids is None:
            return "half_written"
        if len(set(ids)) != len(ids):
            return "counted_twice"
        if before is not None and ids == [e["pass_id"] for e in before]:
            return "old"
        return "new" if len(ids) == 2 else "lost"

    def debris(self) -> list[Path]:
        return _hidden(self.state)


# ---------------------------------------------------------------------------- the study
def _prepare_inputs(work: Path, commands: tuple[str, ...]) -> dict[str, Any]:
    """Small scenarios for the commands (seeded), and an update state holding one pass."""
    from misrgraph.sim.simulate import ScenarioConfig, run_simulate

    inputs: dict[str, Any] = {}
    if "adjust" in commands:
        inputs["pass"] = work / "in_pass"
        run_simulate(
            ScenarioConfig(
                truth="model",
                scenario="pass",
                seed=7,
                n_tie_points=60,
                n_check_points=5,
                duration_s=600.0,
                start_lat_deg=50.0,
            ),
            inputs["pass"],
        )
    if "calibrate" in commands:
        inputs["month"] = work / "in_month"
        run_simulate(ScenarioConfig(truth="model", scenario="month", seed=8, n_gcps=16, month_days=8), inputs["month"])
    if "update" in commands:
        p = work / "in_path"
        run_simulate(
            ScenarioConfig(
                truth="model",
                scenario="path",
                seed=9,
                n_passes=2,
                n_tie_points=30,
                n_check_points=3,
                duration_s=400.0,
                start_lat_deg=50.0,
            ),
            p,
        )
        inputs["path_passes"] = sorted((p / "passes").glob("*.h5"))
        base = work / "base_state"
        _run(
            _cli(
                "update",
                str(base),
                str(inputs["path_passes"][0]),
                "--camera-model",
                str(p / "camera_model.h5"),
                "--gcps",
                str(p / "gcp.h5"),
                "--dem",
                str(p / "dem.h5"),
            )
        )
        inputs["base_state"] = base
    return inputs


def run_kill_trials(
    commands: tuple[str, ...] = KILL_COMMANDS,
    trials: int = 20,
    seed: int = 0,
    workdir: str | os.PathLike[str] | None = None,
    progress: Callable[[str], None] | None = None,
) -> dict[str, Any]:
    """SIGKILL each command ``trials`` times at uniformly random points of its run and count the
    outcomes (see the module docstring). Returns ``{"commands": {name: {...}}, "failures": n}``
    where ``failures`` sums half-written, lost, counted-twice and failed-rerun outcomes."""
    unknown = [c for c in commands if c not in KILL_COMMANDS]
    if unknown:
        raise InputError("commands", unknown, list(KILL_COMMANDS))
    if trials < 1:
        raise InputError("trials", trials, "at least 1")
    rng = np.random.default_rng(seed)
    tmp = None
    if workdir is None:
        tmp = tempfile.TemporaryDirectory(prefix="misrgraph-kill-")
        workdir = tmp.name
    work = Path(workdir)
    work.mkdir(parents=True, exist_ok=True)
    try:
        if progress:
            progress("simulating the inputs")
        inputs = _prepare_inputs(work, commands)
        # kills land in the command's work, after interpreter start-up and imports (measured)
        startup_s = min(_run(_cli("--help")) for _ in range(2))
        classes = {"simulate": _Simulate, "calibrate": _Calibrate, "adjust": _Adjust, "update": _Update}
        report: dict[str, Any] = {}
        for name in commands:
            d = work / f"kill_{name}"
            d.mkdir(exist_ok=True)
            t = classes[name](d, inputs)
            t.reset(1)
            full_s = _run(t.command(0))  # an uninterrupted run: its time sets the kill window
            counts = {k: 0 for k in ("old", "new", "none", *_FAILURES)}
            killed, debris = 0, 0
            for i in range(trials):
                if progress:
                    progress(f"{name}: trial {i + 1}/{trials}")
                t.reset(i)
                before = t.snapshot()
                after = float(rng.uniform(min(startup_s, 0.9 * full_s), full_s))
                killed += _run_and_kill(t.command(i), after)
                outcome = t.judge(before, i)
                counts[outcome] += 1
                left = t.debris()
                debris += len(left)
                for p in left:  # counted once; cleared so the next trial starts clean
                    shutil.rmtree(p, ignore_errors=True) if p.is_dir() else p.unlink(missing_ok=True)
                if outcome in _FAILURES:
                    log.warning("%s trial %d: %s (kill after %.2f s of %.2f s)", name, i, outcome, after, full_s)
                if not t.rerun_ok(i):
                    counts["rerun_failed"] += 1
            report[name] = {
                "trials": trials,
                "killed_while_running": killed,
                "uninterrupted_s": full_s,
                "startup_s": startup_s,
                **counts,
                "debris": debris,
            }
        return {"commands": report, "failures": int(sum(r[k] for r in report.values() for k in _FAILURES))}
    finally:
        if tmp is not None:
            tmp.cleanup()
