"""HDF5 helpers: atomic writes, kind/version stamping and validated reads.

Every misrgraph HDF5 file carries two root attributes: ``misrgraph_kind`` (``"camera_model"``,
``"orbit_pass"``, ``"gcp_database"``, ``"dem"``, ...) and ``format_version`` (an integer per kind).
Writers go through :func:`atomic_h5`: the file is written under a temporary name in the target
directory and renamed into place only when complete, so a crash never leaves a partial file.
Readers go through :func:`open_h5`, which checks kind and version and turns h5py/OS errors into a
one-line :class:`~misrgraph.errors.FileFormatError`.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from pathlib import Path
from typing import Any, Iterator

import h5py
import numpy as np

from misrgraph.errors import FileFormatError

__all__ = ["atomic_h5", "open_h5", "read_dataset", "read_attr", "write_dataset", "FORMAT_VERSIONS"]

FORMAT_VERSIONS: dict[str, int] = {
    "camera_model": 2,
    "orbit_pass": 2,
    "gcp_database": 1,
    "dem": 1,
    "calibration_result": 2,
    "adjustment_result": 2,
    "update_state": 2,
}

#: Why an older version of a kind is refused, when the reason is known (one line each).
_OLD_VERSION_REASON: dict[tuple[str, int], str] = {
    (kind, 1): "version 1 stored camera angles in the retired convention T_ic = Rz(delta) Ry(beta) "
               "(delta as an azimuth); version 2 uses MISR's T_ic = Ry(beta) Rx(delta), and the same "
               "numbers would geolocate kilometres apart. Re-create the file with this version"
    for kind in ("camera_model", "orbit_pass", "calibration_result", "adjustment_result", "update_state")
}


@contextlib.contextmanager
def atomic_h5(path: str | os.PathLike[str], kind: str) -> Iterator[h5py.File]:
    """Open a new HDF5 file for writing that appears at ``path`` only if the block succeeds."""
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent)
    os.close(fd)
    try:
        with h5py.File(tmp, "w") as f:
            f.attrs["misrgraph_kind"] = kind
            f.attrs["format_version"] = FORMAT_VERSIONS[kind]
            yield f
        os.replace(tmp, target)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


@contextlib.contextmanager
def open_h5(path: str | os.PathLike[str], kind: str | None = None) -> Iterator[h5py.File]:
    """Open a misrgraph HDF5 file read-only, validating kind and format version."""
    p = Path(path)
    if not p.exists():
        raise FileFormatError(p, "file does not exist")
    try:
        f = h5py.File(p, "r")
    except OSError as exc:
        raise FileFormatError(p, f"not a readable HDF5 file ({exc.__class__.__name__}: truncated or corrupt?)") from exc
    try:
        got_kind = f.attrs.get("misrgraph_kind")
        if got_kind is None:
            raise FileFormatError(p, "missing root attribute 'misrgraph_kind'; not a misrgraph file")
        got_kind = got_kind.decode() if isinstance(got_kind, bytes) else str(got_kind)
        if kind is not None and got_kind != kind:
            raise FileFormatError(p, f"misrgraph_kind is {got_kind!r}; expected {kind!r}")
        version = f.attrs.get("format_version")
        if isinstance(version, np.generic):
            version = version.item()
        want = FORMAT_VERSIONS.get(got_kind)
        if want is None:
            raise FileFormatError(p, f"unknown misrgraph_kind {got_kind!r}; expected one of {sorted(FORMAT_VERSIONS)}")
        if version is None or int(version) != want:
            why = _OLD_VERSION_REASON.get((got_kind, int(version))) if version is not None else None
            raise FileFormatError(p, f"format_version is {version!r}; expected {want} for kind {got_kind!r}"
                                     + (f" ({why})" if why else ""))
        yield f
    finally:
        f.close()


def read_dataset(
    group: h5py.Group, name: str, shape: tuple[int | None, ...] | None = None, dtype: Any = float
) -> np.ndarray:
    """Read ``group[name]`` fully, checking it exists and has the expected shape (None = any)."""
    where = f"{group.file.filename}: {group.name.rstrip('/')}/{name}"
    if name not in group:
        raise FileFormatError(group.file.filename, f"missing dataset {group.name.rstrip('/')}/{name}")
    obj = group[name]
    if not isinstance(obj, h5py.Dataset):
        raise FileFormatError(group.file.filename, f"{group.name.rstrip('/')}/{name} is not a dataset")
    try:
        data = obj[()]
    except OSError as exc:
        raise FileFormatError(group.file.filename, f"cannot read {group.name.rstrip('/')}/{name}: {exc}") from exc
    arr = np.asarray(data)
    if dtype is not None and arr.dtype.kind not in "SOU":
        arr = arr.astype(dtype)
    if shape is not None:
        ok = len(arr.shape) == len(shape) and all(s is None or s == a for s, a in zip(shape, arr.shape))
        if not ok:
            want = "(" + ", ".join("*" if s is None else str(s) for s in shape) + ")"
            raise FileFormatError(where.split(": ")[0], f"{group.name.rstrip('/')}/{name} has shape {arr.shape}; expected {want}")
    return arr


def read_attr(obj: h5py.HLObject, name: str) -> Any:
    """Read an attribute, raising a clear error when it is missing."""
    if name not in obj.attrs:
        raise FileFormatError(obj.file.filename, f"missing attribute {name!r} on {obj.name}")
    v = obj.attrs[name]
    if isinstance(v, bytes):
        return v.decode()
    if isinstance(v, np.generic):
        return v.item()
    return v


def write_dataset(group: h5py.Group, name: str, data: Any, units: str | None = None, **attrs: Any) -> h5py.Dataset:
    """Create a dataset with optional ``units`` and other attributes."""
    ds = group.create_dataset(name, data=np.asarray(data))
    if units is not None:
        ds.attrs["units"] = units
    for k, v in attrs.items():
        ds.attrs[k] = v
    return ds
