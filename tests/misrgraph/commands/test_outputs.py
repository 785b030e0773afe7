"""Output locations: refused before any work when they cannot be written, a full disk reported in
one line naming the output, and directories and files made with the umask's permissions."""

from __future__ import annotations

import errno
import json
import os
import shutil
import stat
import subprocess
import sys
import time
from pathlib import Path

import h5py
import pytest
from typer.testing import CliRunner

from misrgraph.commands.cli import app
from misrgraph.errors import InputError, OutputError
from misrgraph.io.h5 import atomic_file, atomic_h5, check_writable, write_dataset

runner = CliRunner()
SMALL = ["--tie-points", "20", "--check-points", "5", "--duration", "300", "--gcps", "20"]


def test_unwritable_out_is_refused_before_any_work(tmp_path):
    t0 = time.perf_counter()
    res = runner.invoke(app, ["simulate", "--out", "/proc/misrgraph-x/scenario", *SMALL])
    assert res.exit_code == 2, res.output
    lines = [x for x in res.stderr.splitlines() if x.strip()]
    assert len(lines) == 1 and lines[0].startswith("misrgraph: error: --out:"), res.stderr
    assert "/proc/misrgraph-x/scenario" in lines[0] and "internal error" not in lines[0]
    # the refusal comes before the simulation: far under the seconds a scenario takes
    assert time.perf_counter() - t0 < 2.0


def test_a_file_in_the_way_is_named(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    with pytest.raises(InputError, match="file/out"):
        check_writable(blocker / "out", "--out")


def test_adjust_out_checked_before_adjusting(tmp_path):
    res = runner.invoke(app, ["adjust", str(tmp_path / "no-scenario"), "--out", "/proc/misrgraph-x/r.h5"])
    assert res.exit_code == 2
    assert "--out" in res.stderr and "/proc/misrgraph-x/r.h5" in res.stderr


def _enospc(*args, **kwargs):
    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))


def test_full_disk_in_an_hdf5_writer_names_the_target(tmp_path, monkeypatch):
    target = tmp_path / "out.h5"
    with pytest.raises(OutputError) as err:
        with atomic_h5(target, "dem") as f:
            write_dataset(f, "x", [1.0, 2.0])
            monkeypatch.setattr(h5py.File, "flush", _enospc)
            f.flush()
    assert str(err.value) == f"{target}: cannot write (No space left on device)"
    assert list(tmp_path.iterdir()) == []  # no half-written file, no temporary


def test_full_disk_in_a_plain_writer_names_the_target(tmp_path):
    target = tmp_path / "summary.json"
    with pytest.raises(OutputError, match="summary.json: cannot write"):
        with atomic_file(target) as fh:
            fh.write("{}")
            _enospc()
    assert list(tmp_path.iterdir()) == []


def test_umask_gives_the_modes(tmp_path):
    old = os.umask(0o027)
    try:
        res = runner.invoke(app, ["simulate", "--out", str(tmp_path / "s"), *SMALL, "--json"])
    finally:
        os.umask(old)
    assert res.exit_code == 0, res.output
    assert stat.S_IMODE((tmp_path / "s").stat().st_mode) == 0o750
    assert stat.S_IMODE((tmp_path / "s" / "passes").stat().st_mode) == 0o750
    assert stat.S_IMODE((tmp_path / "s" / "gcp.h5").stat().st_mode) == 0o640
    assert json.loads(res.stdout)["passes"] == 1


def _small_tmpfs(where: Path) -> bool:
    """Mount a 300 KiB tmpfs (root on Linux only); False where that is not allowed."""
    if sys.platform != "linux" or os.geteuid() != 0 or shutil.which("mount") is None:
        return False
    where.mkdir()
    return (
        subprocess.run(["mount", "-t", "tmpfs", "-o", "size=300k", "tmpfs", str(where)], capture_output=True).returncode
        == 0
    )


def test_a_real_full_disk_is_one_line_and_leaves_nothing(tmp_path):
    disk = tmp_path / "full"
    if not _small_tmpfs(disk):
        pytest.skip("no small tmpfs can be mounted here (needs root on Linux)")
    try:
        proc = subprocess.run(
            [sys.executable, "-m", "misrgraph.commands.cli", "simulate", "--out", str(disk / "s"), *SMALL],
            capture_output=True,
            text=True,
            timeout=300,
        )
        leftovers = list(disk.iterdir())
    finally:
        subprocess.run(["umount", str(disk)], capture_output=True)
    assert proc.returncode == 1, proc.stderr
    lines = [x for x in proc.stderr.splitlines() if x.strip() and "━" not in x]
    assert lines == [f"misrgraph: error: {disk / 's'}: cannot write (No space left on device)"], proc.stderr
    assert "Traceback" not in proc.stderr
    assert leftovers == []
