"""Camera geometric model (CGM) versions by orbit range: the versioned model store.

A store is a directory::

    STORE/cgm.json             the index (kind "misrgraph-cgm-store", format 1)
    STORE/versions/<id>.h5     each version's camera-model file (as ``calibrate --out`` writes
                               it: the model, and the calibration's covariance when it has one)

The index lists the versions in the order they were added; each entry holds ``id`` (``v001``,
``v002``, ...), ``file`` (relative to the store), ``sha256`` (the stored file's whole-file
checksum as its checksum block records it, :func:`misrgraph.io.h5.stored_file_sha256`; reading
the file checks its bytes against it),
``first_orbit`` and ``last_orbit`` (inclusive; ``null``: open-ended), ``created_utc``,
``reason`` (what triggered it: free text, e.g. a monitor alarm) and ``source`` (the file it was
added from). The validity ranges never overlap: an open-ended version added while an earlier one
is open-ended closes that one at the orbit before its own first. A pass of orbit ``n`` is adjusted
with the version whose range holds ``n`` (:func:`version_for_orbit`).

Every write of the index is atomic; a stored model is written before the index names it, so a
killed ``cgm add`` leaves the store as it was (and perhaps an unnamed file, which the next add
of that id replaces). ``STORE/.lock`` keeps a second ``cgm add`` out while one runs.
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import fcntl
import json
import os
import shutil
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Iterator

from misrgraph.errors import FileFormatError, InputError, OutputError
from misrgraph.io.h5 import atomic_file, atomic_path, os_reason, stored_file_sha256

__all__ = [
    "CgmVersion",
    "CgmStore",
    "INDEX_NAME",
    "is_cgm_store",
    "open_store",
    "add_version",
    "version_for_orbit",
]

#: The index file of a store.
INDEX_NAME = "cgm.json"
_KIND = "misrgraph-cgm-store"
_FORMAT = 1


@dataclass(frozen=True)
class CgmVersion:
    """One camera-model version: its stored file and the orbits it is valid for (inclusive;
    ``last_orbit`` None: open-ended)."""

    id: str
    file: str
    sha256: str
    first_orbit: int
    last_orbit: int | None
    created_utc: str
    reason: str
    source: str

    def covers(self, orbit: int) -> bool:
        """Whether orbit ``orbit`` is in this version's range."""
        return self.first_orbit <= orbit and (self.last_orbit is None or orbit <= self.last_orbit)

    def orbits_text(self) -> str:
        """The range as text: ``1000-1999`` or ``2000-``."""
        return f"{self.first_orbit}-{'' if self.last_orbit is None else self.last_orbit}"


@dataclass(frozen=True)
class CgmStore:
    """A store's directory and its versions (in the order they were added)."""

    root: Path
    versions: tuple[CgmVersion, ...]

    def path_of(self, version: CgmVersion) -> Path:
        """The stored camera-model file of ``version``."""
        return self.root / version.file

    def get(self, version_id: str) -> CgmVersion:
        """The version named ``version_id``; InputError naming the known ids otherwise."""
        for v in self.versions:
            if v.id == version_id:
                return v
        raise InputError("VERSION", version_id, [v.id for v in self.versions] or "a version of the store (it is empty)")


def is_cgm_store(path: str | os.PathLike[str]) -> bool:
    """Whether ``path`` is a CGM store directory (holds ``cgm.json``)."""
    p = Path(path)
    return p.is_dir() and (p / INDEX_NAME).is_file()


def _version_from(entry: Any, index: Path) -> CgmVersion:
    try:
        last = entry["last_orbit"]
        return CgmVersion(
            id=str(entry["id"]),
            file=str(entry["file"]),
            sha256=str(entry["sha256"]),
            first_orbit=int(entry["first_orbit"]),
            last_orbit=None if last is None else int(last),
            created_utc=str(entry["created_utc"]),
            reason=str(entry.get("reason", "")),
            source=str(entry.get("source", "")),
        )
    except (KeyError, TypeError, ValueError) as exc:
        raise FileFormatError(index, f"a version entry lacks or misstates a field ({exc})") from None


def open_store(path: str | os.PathLike[str]) -> CgmStore:
    """Read a store's index (see the module docstring); FileFormatError when ``path`` is not one."""
    root = Path(path)
    index = root / INDEX_NAME
    if not index.is_file():
        raise FileFormatError(root, f"not a CGM store (no {INDEX_NAME}; 'misrgraph cgm add' creates one)")
    try:
        doc = json.loads(index.read_text())
    except OSError as exc:
        raise FileFormatError(index, f"cannot read ({exc.strerror})") from None
    except ValueError as exc:
        raise FileFormatError(index, f"not JSON ({exc})") from None
    if not isinstance(doc, dict) or doc.get("kind") != _KIND:
        raise FileFormatError(index, f"kind {doc.get('kind') if isinstance(doc, dict) else None!r}; expected {_KIND!r}")
    if doc.get("format") != _FORMAT:
        raise FileFormatError(index, f"format {doc.get('format')!r}; this misrgraph reads format {_FORMAT}")
    versions = tuple(_version_from(e, index) for e in doc.get("versions", []))
    return CgmStore(root=root, versions=versions)


def _write_index(store: CgmStore) -> None:
    doc = {"kind": _KIND, "format": _FORMAT, "versions": [asdict(v) for v in store.versions]}
    with atomic_file(store.root / INDEX_NAME) as fh:
        json.dump(doc, fh, indent=2)
        fh.write("\n")


def add_version(
    store_dir: str | os.PathLike[str],
    camera_model: str | os.PathLike[str],
    first_orbit: int,
    last_orbit: int | None = None,
    reason: str = "",
    now: _dt.datetime | None = None,
) -> CgmVersion:
    """Add a camera-model file as a new version valid from ``first_orbit`` to ``last_orbit``
    (inclusive; None: open-ended), creating the store if needed, and return it.

    An open-ended new version closes an open-ended version that starts before it at
    ``first_orbit - 1``. Any other overlap with an existing range is refused, as is a file that
    is not a camera model (it is read first)."""
    from misrgraph.io.camera import read_camera_file

    root = Path(store_dir)
    if first_orbit < 0:
        raise InputError("--from-orbit", first_orbit, "an orbit number >= 0")
    if last_orbit is not None and last_orbit < first_orbit:
        raise InputError("--to-orbit", last_orbit, f"an orbit >= --from-orbit ({first_orbit})")
    src = Path(camera_model)
    read_camera_file(src)  # a camera-model file, whole and readable (names the path otherwise)
    if root.exists() and not root.is_dir():
        raise InputError("STORE", str(root), "a directory (a CGM store, or a place for a new one)")
    with _store_lock(root):
        return _add_locked(root, src, first_orbit, last_orbit, reason, now)


@contextlib.contextmanager
def _store_lock(root: Path) -> Iterator[None]:
    """Hold ``STORE/.lock`` exclusively: one ``cgm add`` at a time (a second one is refused)."""
    try:
        root.mkdir(parents=True, exist_ok=True)
        fh = open(root / ".lock", "a+")
    except OSError as exc:
        raise OutputError(root, os_reason(exc)) from None
    with fh:
        try:
            fcntl.flock(fh.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            raise InputError("STORE", str(root), "a store no other 'cgm add' is changing (it holds the lock)") from None
        yield


def _add_locked(
    root: Path, src: Path, first_orbit: int, last_orbit: int | None, reason: str, now: _dt.datetime | None
) -> CgmVersion:
    store = open_store(root) if is_cgm_store(root) else CgmStore(root=root, versions=())
    versions = list(store.versions)
    for i, v in enumerate(versions):
        ends_after = v.last_orbit is None or v.last_orbit >= first_orbit
        starts_before = last_orbit is None or v.first_orbit <= last_orbit
        if not (ends_after and starts_before):
            continue
        if v.last_orbit is None and v.first_orbit < first_orbit and last_orbit is None:
            versions[i] = CgmVersion(**{**asdict(v), "last_orbit": first_orbit - 1})
            continue
        new_range = f"{first_orbit}-{'' if last_orbit is None else last_orbit}"
        raise InputError("--from-orbit/--to-orbit", new_range, f"orbits outside version {v.id}'s {v.orbits_text()}")
    vid = f"v{len(versions) + 1:03d}"
    rel = f"versions/{vid}.h5"
    with atomic_path(root / rel) as tmp:
        shutil.copyfile(src, tmp)
    stamp = (now or _dt.datetime.now(_dt.timezone.utc)).strftime("%Y-%m-%dT%H:%M:%SZ")
    new = CgmVersion(
        id=vid,
        file=rel,
        sha256=stored_file_sha256(root / rel),
        first_orbit=int(first_orbit),
        last_orbit=None if last_orbit is None else int(last_orbit),
        created_utc=stamp,
        reason=reason,
        source=str(src.resolve()),
    )
    _write_index(CgmStore(root=root, versions=(*versions, new)))
    return new


def version_for_orbit(store: CgmStore, orbit: int) -> tuple[CgmVersion, Path]:
    """The version valid for ``orbit`` and its stored file (its digest checked); InputError
    listing the ranges when none covers it."""
    for v in store.versions:
        if v.covers(orbit):
            path = store.path_of(v)
            if not path.is_file():
                raise FileFormatError(path, f"version {v.id}'s camera model is missing from the store")
            if stored_file_sha256(path) != v.sha256:
                raise FileFormatError(path, f"version {v.id}'s camera model differs from the one stored (sha256)")
            return v, path
    ranges = ", ".join(f"{v.id} {v.orbits_text()}" for v in store.versions) or "none (the store is empty)"
    raise InputError("orbit", orbit, f"an orbit some version of {store.root} covers ({ranges})")
