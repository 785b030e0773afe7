"""HDF5 helpers: atomic writes, kind/version stamping and validated reads.

Every misrgraph HDF5 file carries two root attributes: ``misrgraph_kind`` (``"camera_model"``,
``"orbit_pass"``, ``"gcp_database"``, ``"dem"``, ...) and ``format_version`` (an integer per kind).
Writers go through :func:`atomic_h5`: the file is written under a temporary name in the target
directory and renamed into place only when complete, so a crash never leaves a partial file.
Readers go through :func:`open_h5`, which checks kind and version and turns h5py/OS errors into a
one-line :class:`~misrgraph.errors.FileFormatError`.

Integrity: every numeric dataset is written with HDF5's Fletcher-32 checksum, and every file
carries ``content_sha256``, a SHA-256 over the names, types, shapes and bytes of all its datasets
and attributes (:func:`content_digest`), stamped just before the rename. :func:`open_h5` reads
every dataset and verifies both, so a damaged file is refused with the dataset that failed (or
"content digest mismatch") before any of it is used. The write is durable: the file and its
directory are fsynced around the rename, and the file gets the mode the umask allows.

Before HDF5 parses a byte, the file as a whole is checked: every file starts with a 512-byte HDF5
user block holding ``MISRGRAPH-SHA256`` and the SHA-256 of everything after the block
(:func:`file_checksum_ok`). HDF5's own parser can loop for ever or crash on damaged metadata, so a
damaged file must never reach it; the in-file checksums and digest then guard the content as
HDF5 sees it.
"""

from __future__ import annotations

import contextlib
import errno
import hashlib
import os
import re
import tempfile
from pathlib import Path
from typing import Any, Iterator

import h5py
import numpy as np

from misrgraph.errors import FileFormatError, InputError, OutputError

__all__ = [
    "check_writable",
    "make_temp_dir",
    "dir_mode",
    "os_reason",
    "is_write_failure",
    "atomic_h5",
    "atomic_path",
    "open_h5",
    "read_dataset",
    "read_attr",
    "write_dataset",
    "create_dataset",
    "FORMAT_VERSIONS",
    "require_group",
    "DIGEST_ATTR",
    "content_digest",
    "stamp_content_digest",
    "fsync_directory",
    "file_mode",
    "USERBLOCK_SIZE",
    "file_checksum_ok",
    "reseal",
    "stored_file_sha256",
    "atomic_file",
]

FORMAT_VERSIONS: dict[str, int] = {
    "camera_model": 2,
    "orbit_pass": 2,
    "gcp_database": 2,
    "dem": 3,
    "calibration_result": 2,
    "adjustment_result": 2,
    "update_state": 2,
    "projection_parameters": 1,
    "som_dem": 1,
    "reference_orbit_imagery": 2,
}

#: Why an older version of a kind is refused, when the reason is known (one line each).
_OLD_VERSION_REASON: dict[tuple[str, int], str] = {
    (kind, 1): "version 1 stored camera angles in the retired convention T_ic = Rz(delta) Ry(beta) "
    "(delta as an azimuth); version 2 uses MISR's T_ic = Ry(beta) Rx(delta), and the same "
    "numbers would geolocate kilometres apart. Re-create the file with this version"
    for kind in ("camera_model", "orbit_pass", "calibration_result", "adjustment_result", "update_state")
}
_OLD_VERSION_REASON.update(
    {
        (kind, 1): "version 1 files carry no checksums or content digest; re-create the file with this version"
        for kind in ("gcp_database", "dem")
    }
)
_OLD_VERSION_REASON[("reference_orbit_imagery", 1)] = (
    "version 1 ROI files have no /obscured layer and hold pixels that terrain hides from the camera "
    "(resampled from the terrain in front of them); rebuild the ROI with this version"
)
_OLD_VERSION_REASON[("dem", 2)] = (
    "version 2 DEMs have 3-arcsecond longitude postings at every latitude (no "
    "/tiles/lon_posting, DTED's zones); re-create the file with this version"
)

#: Root attribute holding the SHA-256 content digest (hex) of a file.
DIGEST_ATTR = "content_sha256"

#: Size (bytes) of the HDF5 user block that carries the whole-file SHA-256.
USERBLOCK_SIZE = 512
_USERBLOCK_MAGIC = b"MISRGRAPH-SHA256 "


def _sha256_after_userblock(path: str | os.PathLike[str]) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        fh.seek(USERBLOCK_SIZE)
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def _write_userblock(path: str | os.PathLike[str]) -> None:
    header = _USERBLOCK_MAGIC + _sha256_after_userblock(path).encode() + b"\n"
    with open(path, "rb+") as fh:
        fh.write(header.ljust(USERBLOCK_SIZE, b"\x00"))
        fh.flush()
        os.fsync(fh.fileno())


def reseal(path: str | os.PathLike[str]) -> None:
    """Re-write the whole-file SHA-256 of a misrgraph file edited in place with h5py (an expert
    tool: the in-file content digest still has to be re-stamped with
    :func:`stamp_content_digest` for the edit to be accepted)."""
    _write_userblock(path)


def _userblock_sha256(path: str | os.PathLike[str]) -> str | None:
    """The SHA-256 (hex) recorded in the user block, or None if there is no misrgraph block."""
    with open(path, "rb") as fh:
        head = fh.read(USERBLOCK_SIZE)
    if len(head) < USERBLOCK_SIZE or not head.startswith(_USERBLOCK_MAGIC):
        return None
    return head[len(_USERBLOCK_MAGIC) : len(_USERBLOCK_MAGIC) + 64].decode("ascii", "replace")


def stored_file_sha256(path: str | os.PathLike[str]) -> str:
    """The whole-file SHA-256 (hex) recorded in a misrgraph file's user block, without hashing
    the file (:func:`open_h5` verifies it on every read). FileFormatError without one."""
    stored = _userblock_sha256(path)
    if stored is None:
        raise FileFormatError(path, "no misrgraph checksum block at the start of the file")
    return stored


def file_checksum_ok(path: str | os.PathLike[str]) -> tuple[bool, str]:
    """Check the whole-file SHA-256 in the user block without letting HDF5 parse the file.

    Returns ``(ok, reason)``; ``reason`` says what is wrong (one line) when ``ok`` is False."""
    stored = _userblock_sha256(path)
    if stored is None:
        return False, (
            "no misrgraph checksum block at the start of the file (damaged, not written by "
            "misrgraph, or written by a version before this check)"
        )
    got = _sha256_after_userblock(path)
    if stored != got:
        return False, f"file checksum mismatch (stored {stored[:12]}..., computed {got[:12]}...): the file is damaged"
    return True, ""


def _value_bytes(v: Any) -> bytes:
    arr = np.asarray(v)
    if arr.dtype.kind in "OSU":
        items = [x.decode() if isinstance(x, bytes) else str(x) for x in arr.ravel()]
        return ("\x00".join(items) + f"|{arr.shape}").encode()
    return np.ascontiguousarray(arr).tobytes() + f"|{arr.dtype.str}|{arr.shape}".encode()


def content_digest(f: h5py.File) -> str:
    """SHA-256 (hex) over every dataset's and attribute's name, type, shape and bytes, in name
    order, leaving out :data:`DIGEST_ATTR` itself. Reading a dataset whose Fletcher-32 checksum
    fails raises :class:`FileFormatError` naming it."""
    h = hashlib.sha256()

    def attrs(obj: Any) -> None:
        for k in sorted(obj.attrs):
            if obj.name == "/" and k == DIGEST_ATTR:
                continue
            h.update(f"@{obj.name}:{k}=".encode())
            h.update(_value_bytes(obj.attrs[k]))

    def walk(group: Any) -> None:
        attrs(group)
        for name in sorted(group):
            obj = group[name]
            if isinstance(obj, h5py.Group):
                walk(obj)
                continue
            try:
                data = obj[()]
            except OSError as exc:
                raise FileFormatError(
                    f.filename, f"dataset {obj.name} failed its checksum or cannot be read ({exc}); the file is damaged"
                ) from exc
            h.update(f"#{obj.name}=".encode())
            h.update(_value_bytes(data))
            attrs(obj)

    walk(f)
    return h.hexdigest()


def stamp_content_digest(f: h5py.File) -> None:
    """Write :data:`DIGEST_ATTR` for a file open for writing (done by :func:`atomic_h5`)."""
    f.attrs[DIGEST_ATTR] = content_digest(f)


def file_mode() -> int:
    """The mode a new file gets under the current umask (0o666 & ~umask)."""
    mask = os.umask(0)
    os.umask(mask)
    return 0o666 & ~mask


def dir_mode() -> int:
    """The mode a new directory gets under the current umask (0o777 & ~umask)."""
    mask = os.umask(0)
    os.umask(mask)
    return 0o777 & ~mask


def make_temp_dir(prefix: str, parent: str | os.PathLike[str], suffix: str = "") -> Path:
    """A hidden temporary directory in ``parent`` (created if missing) with the umask's mode
    (``mkdtemp`` alone gives 0700, which the directory would keep once renamed into place)."""
    Path(parent).mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=prefix, suffix=suffix, dir=parent))
    os.chmod(tmp, dir_mode())
    return tmp


#: errno values that mean the place cannot take the output (not a bug, not an input's fault)
_WRITE_ERRNOS = {errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EACCES, errno.EPERM, errno.EIO, errno.EFBIG}


def _errno_of(exc: OSError) -> int | None:
    if exc.errno is not None:
        return exc.errno
    m = re.search(r"errno = (\d+)", str(exc))
    return int(m.group(1)) if m else None


def is_write_failure(exc: BaseException) -> bool:
    """True for an OSError that says the place cannot take the output (full disk, read-only, ...)."""
    return isinstance(exc, OSError) and _errno_of(exc) in _WRITE_ERRNOS


def os_reason(exc: OSError) -> str:
    """The operating system's reason for an I/O failure, without a library's detail (HDF5's
    messages carry ``errno = N`` inside a long text)."""
    code = _errno_of(exc)
    if code:
        return os.strerror(code)
    return str(exc).splitlines()[0][:160] if str(exc) else exc.__class__.__name__


def check_writable(path: str | os.PathLike[str], field: str) -> None:
    """Refuse, before any work, an output at ``path`` that cannot be written.

    Nothing is left behind: a temporary file is made and removed in the nearest directory that
    exists on the way to ``path`` (the directories below it are created later, by the writer).

    Raises
    ------
    InputError
        Naming ``field``, the path and the operating system's reason.
    """
    parent = Path(path).absolute().parent
    while not parent.exists() and parent != parent.parent:
        parent = parent.parent
    try:
        if not parent.is_dir():
            raise NotADirectoryError(errno.ENOTDIR, os.strerror(errno.ENOTDIR), str(parent))
        fd, tmp = tempfile.mkstemp(prefix=".misrgraph-write-check.", dir=parent)
        os.close(fd)
        os.unlink(tmp)
    except OSError as exc:
        raise InputError(field, str(path), f"a place that can be written ({parent}: {os_reason(exc)})") from None


def fsync_directory(path: str | os.PathLike[str]) -> None:
    """fsync a directory so that a rename inside it survives a crash (no-op where unsupported)."""
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:  # pragma: no cover - platforms without directory handles
        return
    try:
        os.fsync(fd)
    except OSError:  # pragma: no cover
        pass
    finally:
        os.close(fd)


@contextlib.contextmanager
def atomic_file(path: str | os.PathLike[str], binary: bool = False) -> Iterator[Any]:
    """Open a plain file for writing that appears at ``path`` only if the block succeeds: a hidden
    temporary in the same directory, fsynced, given the umask's mode, renamed, directory fsynced."""
    target = Path(path)
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent)
    except OSError as exc:
        raise OutputError(target, os_reason(exc)) from None
    try:
        with os.fdopen(fd, "wb" if binary else "w") as fh:
            yield fh
            fh.flush()
            os.fsync(fh.fileno())
        os.chmod(tmp, file_mode())
        os.replace(tmp, target)
    except BaseException as exc:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        if is_write_failure(exc):
            raise OutputError(target, os_reason(exc)) from exc
        raise
    fsync_directory(target.parent)


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike[str]) -> Iterator[str]:
    """A temporary path for a library that writes a file by name (h5py, HDF4): hidden, in
    ``path``'s directory (created if needed), no file there yet. When the block succeeds the file
    is fsynced, given the umask's mode and renamed to ``path``, and the directory fsynced; when it
    fails the file is removed, and a full disk or an unwritable place is an
    :class:`~misrgraph.errors.OutputError` naming ``path``."""
    target = Path(path)
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent)
    except OSError as exc:
        raise OutputError(target, os_reason(exc)) from None
    os.close(fd)
    os.unlink(tmp)  # the library creates it
    try:
        yield tmp
        with open(tmp, "rb+") as fh:
            os.fsync(fh.fileno())
        os.chmod(tmp, file_mode())
        os.replace(tmp, target)
        fsync_directory(target.parent)
    except BaseException as exc:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        if is_write_failure(exc):
            raise OutputError(target, os_reason(exc)) from exc
        raise


@contextlib.contextmanager
def atomic_h5(path: str | os.PathLike[str], kind: str) -> Iterator[h5py.File]:
    """Open a new HDF5 file for writing that appears at ``path`` only if the block succeeds."""
    with atomic_path(path) as tmp:
        with h5py.File(tmp, "w", userblock_size=USERBLOCK_SIZE) as f:
            f.attrs["misrgraph_kind"] = kind
            f.attrs["format_version"] = FORMAT_VERSIONS[kind]
            yield f
            stamp_content_digest(f)
        _write_userblock(tmp)  # whole-file SHA-256


def _validate(f: h5py.File, p: Path, kind: str | None) -> None:
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
        raise FileFormatError(
            p, f"format_version is {version!r}; expected {want} for kind {got_kind!r}" + (f" ({why})" if why else "")
        )
    stored = f.attrs.get(DIGEST_ATTR)
    if stored is None:
        raise FileFormatError(p, f"no {DIGEST_ATTR} attribute: the file was not completed by misrgraph or was altered")
    stored = stored.decode() if isinstance(stored, bytes) else str(stored)
    got = content_digest(f)
    if got != stored:
        raise FileFormatError(
            p,
            f"content digest mismatch (stored {stored[:12]}..., computed {got[:12]}...): "
            "the file is damaged or was altered",
        )


@contextlib.contextmanager
def open_h5(path: str | os.PathLike[str], kind: str | None = None) -> Iterator[h5py.File]:
    """Open a misrgraph HDF5 file read-only after validating kind, format version, every
    dataset's checksum and the content digest (see the module docstring)."""
    p = Path(path)
    if not p.exists():
        raise FileFormatError(p, "file does not exist")
    try:
        ok, why = file_checksum_ok(p)
    except OSError as exc:
        raise FileFormatError(p, f"cannot read ({exc.__class__.__name__}: {exc})") from exc
    if not ok:
        raise FileFormatError(p, why)
    try:
        f = h5py.File(p, "r")
    except OSError as exc:
        raise FileFormatError(p, f"not a readable HDF5 file ({exc.__class__.__name__}: truncated or corrupt?)") from exc
    try:
        _validate(f, p, kind)
    except FileFormatError:
        f.close()
        raise
    except Exception as exc:  # h5py raises many kinds on damaged metadata
        f.close()
        raise FileFormatError(p, f"unreadable ({exc.__class__.__name__}: {exc}); the file is damaged") from exc
    try:
        yield f
    finally:
        f.close()


def require_group(parent: h5py.Group, name: str) -> h5py.Group:
    """``parent[name]`` as a group, or a :class:`FileFormatError` naming the missing path."""
    path = f"{parent.name.rstrip('/')}/{name}"
    obj = parent.get(name)
    if not isinstance(obj, h5py.Group):
        raise FileFormatError(
            parent.file.filename, f"missing group {path}" if obj is None else f"{path} is not a group"
        )
    return obj


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
            raise FileFormatError(
                where.split(": ")[0], f"{group.name.rstrip('/')}/{name} has shape {arr.shape}; expected {want}"
            )
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


def create_dataset(group: h5py.Group, name: str, data: Any, **options: Any) -> h5py.Dataset:
    """``group.create_dataset`` with a Fletcher-32 checksum wherever HDF5 allows one (arrays of
    fixed-size types; not scalars or variable-length strings). ``options`` go to h5py."""
    arr = data if options.get("dtype") is not None else np.asarray(data)
    if np.ndim(arr) >= 1 and np.asarray(arr).dtype.kind not in "OU" and options.get("dtype") is None:
        options.setdefault("fletcher32", True)
    return group.create_dataset(name, data=arr, **options)


def write_dataset(group: h5py.Group, name: str, data: Any, units: str | None = None, **attrs: Any) -> h5py.Dataset:
    """Create a dataset (with its checksum, see :func:`create_dataset`), optional ``units`` and
    other attributes."""
    ds = create_dataset(group, name, np.asarray(data))
    if units is not None:
        ds.attrs["units"] = units
    for k, v in attrs.items():
        ds.attrs[k] = v
    return ds
