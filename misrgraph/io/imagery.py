"""Image windows and GCP chips stored in a pass file (``/imagery``), and matched observations
(``/matched``).

Layout (HDF5, chunked and gzip-compressed pixels)::

    /imagery                  attrs: snr, cloud_fraction, search_px, full_scale_dn
      tie/ gcp/               one group per window kind, W windows of S x S pixels each:
        landmark (W,)           row into /landmarks
        camera, band (W,)       indices
        line0, sample0 (W,)     image line and sample of pixel (0, 0) (exposure index, sample)
        pixels (W, S, S)        uint16 counts (14 bits)
      chips/                  reference chips of the GCPs in the pass (G' chip sets: GCP x band):
        landmark (G',)          row into /landmarks
        band (G',)              band index (absent in files of one band: the attribute band)
        pixels (G', 9, C, C)    float32 counts of another sensor, NaN where a camera does not see it
    /matched                  what misrgraph match measured: landmarks/{id, kind, gcp_index} and
                              observations/{landmark, camera, band, line, sample, exposure, sigma_px}
                              as in the pass; /truth/matched/{landmark_ecef, blunder} when simulated

Pixel ``(r, q)`` of a window is image line ``line0 + r`` (the exposure at ``t0 + (line0 + r)
line_time``, focal-plane fraction 0) and sample ``sample0 + q``: a matched position there is the
continuous observation the estimator adjusts.
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator

import h5py
import numpy as np
from numpy.typing import NDArray

from misrgraph.errors import FileFormatError, InputError
from misrgraph.io.h5 import (
    create_dataset,
    file_mode,
    fsync_directory,
    open_h5,
    read_dataset,
    reseal,
    stamp_content_digest,
    write_dataset,
)
from misrgraph.io.passes import Landmarks, Observations
from misrgraph.model.constants import CAMERAS
from misrgraph.model.dem import bilinear

__all__ = [
    "ImageWindows",
    "ImageStrip",
    "PassImagery",
    "read_strip",
    "strip_cameras",
    "StripReader",
    "open_strips",
    "write_imagery",
    "read_imagery",
    "has_imagery",
    "MatchedSet",
    "write_matched",
    "read_matched",
    "read_matched_summary",
    "has_matched",
    "OBSERVATION_SETS",
    "INTEREST_RADIUS_PX",
]

#: how far (px) from a tie window's centre the matcher may place its interest point (the renderer
#: sizes tie windows for it)
INTEREST_RADIUS_PX = 3

#: the observation sets a pass file can hold
OBSERVATION_SETS = ("simulated", "matched")

Array = NDArray[np.float64]


@dataclass
class ImageWindows:
    """``W`` square windows: ``landmark, camera, band, line0, sample0 (W,)`` ints and ``pixels (W, S, S)``."""

    landmark: NDArray[np.int64]
    camera: NDArray[np.int64]
    band: NDArray[np.int64]
    line0: NDArray[np.int64]
    sample0: NDArray[np.int64]
    pixels: NDArray[np.uint16]

    def __post_init__(self) -> None:
        n = int(np.asarray(self.landmark).size)
        for name in ("landmark", "camera", "band", "line0", "sample0"):
            arr = np.asarray(getattr(self, name), dtype=np.int64).ravel()
            if arr.size != n:
                raise InputError(f"imagery.{name}", arr.size, f"{n} values (one per window)")
            setattr(self, name, arr)
        px = np.asarray(self.pixels)
        if px.ndim != 3 or px.shape[0] != n or px.shape[1] != px.shape[2]:
            raise InputError("imagery.pixels", px.shape, f"shape ({n}, S, S)")
        self.pixels = px

    def __len__(self) -> int:
        return int(self.landmark.size)

    @property
    def size(self) -> int:
        return int(self.pixels.shape[1]) if self.pixels.ndim == 3 and self.pixels.shape[0] else 0

    def find(self, landmark: int, camera: int, band: int) -> int | None:
        """Index of the window of ``landmark`` in ``camera``/``band``, or None."""
        hit = np.flatnonzero((self.landmark == landmark) & (self.camera == camera) & (self.band == band))
        return int(hit[0]) if hit.size else None

    @classmethod
    def empty(cls, size: int) -> "ImageWindows":
        z = np.zeros(0, np.int64)
        return cls(z, z, z, z, z, np.zeros((0, size, size), np.uint16))


@dataclass
class ImageStrip:
    """Whole image lines of one camera/band: pixel ``(r, q)`` of ``pixels (L, S)`` (uint16 counts)
    is exposure ``line0 + r``, sample ``sample0 + q``."""

    camera: str
    band: int
    line0: int
    sample0: int
    pixels: NDArray[np.uint16]

    def __post_init__(self) -> None:
        px = np.asarray(self.pixels)
        if px.ndim != 2 or 0 in px.shape:
            raise InputError(f"strips.{self.camera}.pixels", px.shape, "shape (lines, samples), both > 0")
        self.pixels = px

    @property
    def lines(self) -> tuple[int, int]:
        """First and one-past-last exposure the strip holds."""
        return self.line0, self.line0 + int(self.pixels.shape[0])

    def sample_at(self, line: Array, sample: Array) -> Array:
        """Counts at continuous image positions (bilinear between pixel centres; NaN outside the
        strip). ``line``, ``sample`` any shape; returns float32 of that shape."""
        r = np.asarray(line, dtype=float) - self.line0
        q = np.asarray(sample, dtype=float) - self.sample0
        return bilinear(self.pixels, r, q).astype(np.float32)


@dataclass
class PassImagery:
    """Windows around tie/check features and GCPs, the GCPs' reference chips and, optionally,
    whole-swath strips per camera (the lines over the blocks Reference Orbit Imagery is made of)."""

    tie: ImageWindows
    gcp: ImageWindows
    chip_landmark: NDArray[np.int64]
    chips: NDArray[np.float32]
    attrs: dict[str, Any]
    strips: dict[str, ImageStrip] = dataclasses.field(default_factory=dict)
    #: band of each chip set (None: all in the tie band, ``attrs["band"]``)
    chip_band: NDArray[np.int64] | None = None

    @property
    def band(self) -> int:
        """The tie points' band (index into :data:`misrgraph.model.constants.BANDS`; red by default)."""
        return int(self.attrs.get("band", 2))

    def chip_index(self) -> dict[tuple[int, int], int]:
        """``{(landmark row, band): chip set}``: which of ``chips`` holds a GCP's chips in a band."""
        bands = np.full(self.chip_landmark.size, self.band) if self.chip_band is None else self.chip_band
        return {(int(r), int(b)): i for i, (r, b) in enumerate(zip(self.chip_landmark, bands))}


def _write_windows(g: Any, w: ImageWindows) -> None:
    for name in ("landmark", "camera", "band", "line0", "sample0"):
        write_dataset(g, name, getattr(w, name))
    s = max(w.size, 1)
    create_dataset(
        g,
        "pixels",
        w.pixels,
        chunks=(1, s, s) if len(w) else None,
        compression="gzip",
        compression_opts=4,
        shuffle=True,
    )
    g["pixels"].attrs["units"] = "counts (14 bit)"


def _read_windows(g: Any) -> ImageWindows:
    n = g["landmark"].shape[0]
    cols = [read_dataset(g, name, (n,), dtype=np.int64) for name in ("landmark", "camera", "band", "line0", "sample0")]
    px = np.asarray(g["pixels"][...])
    return ImageWindows(*cols, px)


def write_imagery(f: Any, imagery: PassImagery) -> None:
    """Write ``/imagery`` into an open pass file."""
    g = f.create_group("imagery")
    for k, v in imagery.attrs.items():
        g.attrs[k] = v
    _write_windows(g.create_group("tie"), imagery.tie)
    _write_windows(g.create_group("gcp"), imagery.gcp)
    c = g.create_group("chips")
    write_dataset(c, "landmark", imagery.chip_landmark)
    write_dataset(
        c,
        "band",
        np.full(imagery.chip_landmark.size, imagery.band, np.int64)
        if imagery.chip_band is None
        else np.asarray(imagery.chip_band, np.int64),
    )
    create_dataset(c, "pixels", imagery.chips, compression="gzip", compression_opts=4, shuffle=True)
    if imagery.strips:
        sg = g.create_group("strips")
        for name, st in imagery.strips.items():
            cg = sg.create_group(name)
            cg.attrs["band"] = int(st.band)
            cg.attrs["line0"] = int(st.line0)
            cg.attrs["sample0"] = int(st.sample0)
            create_dataset(
                cg,
                "pixels",
                st.pixels,
                chunks=(min(64, st.pixels.shape[0]), min(256, st.pixels.shape[1])),
                compression="gzip",
                compression_opts=4,
                shuffle=True,
            )
            cg["pixels"].attrs["units"] = "counts (14 bit)"


class StripReader:
    """The whole-swath strips of one pass file opened (and validated) once: which cameras it
    holds, the blocks they were rendered for, and any camera's lines (read as sliced). ``file``
    is the open pass file, for reading anything else from it without validating it again."""

    def __init__(self, f: Any, path: str | os.PathLike[str]) -> None:
        self.path = path
        self.file = f
        g = f.get("imagery")
        self._group = g["strips"] if g is not None and "strips" in g else None
        self._attrs = g.attrs if g is not None else {}

    @property
    def cameras(self) -> tuple[str, ...]:
        """The cameras with strips, in MISR's order (none: ``()``)."""
        return () if self._group is None else tuple(n for n in CAMERAS if n in self._group)

    @property
    def blocks(self) -> tuple[int, int] | None:
        """The blocks ``(first, last)`` the strips were rendered for (None: no strips)."""
        if self._group is None or "roi_blocks" not in self._attrs:
            return None
        a, b = (int(v) for v in np.asarray(self._attrs["roi_blocks"]).ravel()[:2])
        return a, b

    def strip(self, camera: str, lines: tuple[int, int] | None = None) -> ImageStrip | None:
        """One camera's strip (FileFormatError naming what is missing), or only its exposures
        ``lines = (first, one past last)`` (None when the strip holds none of them)."""
        if self._group is None:
            raise FileFormatError(self.path, "no /imagery/strips: simulate with --imagery --roi-blocks A-B")
        if camera not in self._group:
            raise FileFormatError(self.path, f"no strip of camera {camera} (it holds {', '.join(sorted(self._group))})")
        cg = self._group[camera]
        try:
            band, line0, sample0 = (int(cg.attrs[k]) for k in ("band", "line0", "sample0"))
        except KeyError as exc:
            raise FileFormatError(self.path, f"/imagery/strips/{camera} lacks the attribute {exc}") from None
        px = cg["pixels"]
        if px.ndim != 2:
            raise FileFormatError(
                self.path, f"/imagery/strips/{camera}/pixels has shape {px.shape}; expected (lines, samples)"
            )
        if lines is None:
            return ImageStrip(camera, band, line0, sample0, np.asarray(px[...]))
        a, b = max(int(lines[0]) - line0, 0), min(int(lines[1]) - line0, px.shape[0])
        return ImageStrip(camera, band, line0 + a, sample0, np.asarray(px[a:b])) if b - a >= 2 else None


@contextlib.contextmanager
def open_strips(path: str | os.PathLike[str]) -> Iterator[StripReader]:
    """A :class:`StripReader` of a pass file, valid inside the block (the file is validated once
    on opening: keep it open to read many strips)."""
    with open_h5(path, "orbit_pass") as f:
        yield StripReader(f, path)


def strip_cameras(path: str | os.PathLike[str]) -> tuple[str, ...]:
    """The cameras whose whole-swath strips a pass file holds (none: ``()``)."""
    with open_strips(path) as r:
        return r.cameras


def read_strip(path: str | os.PathLike[str], camera: str, lines: tuple[int, int] | None = None) -> ImageStrip | None:
    """One camera's whole-swath strip of a pass file (:meth:`StripReader.strip`)."""
    with open_strips(path) as r:
        return r.strip(camera, lines)


def has_imagery(path: str | os.PathLike[str]) -> bool:
    with open_h5(path, "orbit_pass") as f:
        return "imagery" in f


def read_imagery(path: str | os.PathLike[str]) -> PassImagery:
    """The ``/imagery`` of a pass file (FileFormatError if it has none)."""
    with open_h5(path, "orbit_pass") as f:
        if "imagery" not in f:
            raise FileFormatError(path, "no /imagery group: simulate with --imagery (or supply imagery)")
        g = f["imagery"]
        c = g["chips"]
        n = c["landmark"].shape[0]
        return PassImagery(
            _read_windows(g["tie"]),
            _read_windows(g["gcp"]),
            read_dataset(c, "landmark", (n,), dtype=np.int64),
            np.asarray(c["pixels"][...]),
            {k: (v.tolist() if hasattr(v, "tolist") else v) for k, v in g.attrs.items()},
            chip_band=read_dataset(c, "band", (n,), dtype=np.int64) if "band" in c else None,
        )


# ---------------------------------------------------------------------------- matched observations
@dataclass
class MatchedSet:
    """Observations measured by matching: their own landmarks (a tie point is defined by the An
    interest point it was matched from) and, for simulated passes, their truth."""

    landmarks: Landmarks
    observations: Observations
    truth_landmark_ecef: Array | None = None
    truth_blunder: NDArray[np.bool_] | None = None
    summary: dict[str, Any] | None = None


def has_matched(path: str | os.PathLike[str]) -> bool:
    with open_h5(path, "orbit_pass") as f:
        return "matched" in f


def write_matched(path: str | os.PathLike[str], matched: MatchedSet) -> None:
    """Replace ``/matched`` (and ``/truth/matched``) of a pass file, atomically: the file is copied,
    changed and renamed over the original, so a failure leaves the original intact."""
    import json

    path = Path(path)
    fd, tmp_name = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    tmp = Path(tmp_name)
    try:
        shutil.copyfile(path, tmp)
        with h5py.File(tmp, "r+") as f:
            if "matched" in f:
                del f["matched"]
            m = f.create_group("matched")
            if matched.summary is not None:
                m.attrs["summary_json"] = json.dumps(matched.summary)
            lg = m.create_group("landmarks")
            write_dataset(lg, "id", matched.landmarks.id)
            write_dataset(lg, "kind", matched.landmarks.kind)
            write_dataset(lg, "gcp_index", matched.landmarks.gcp_index)
            og = m.create_group("observations")
            o = matched.observations
            for name in ("landmark", "camera", "band", "line", "sample", "exposure", "sigma_px"):
                write_dataset(og, name, getattr(o, name))
            if "truth" in f and "matched" in f["truth"]:
                del f["truth"]["matched"]
            if matched.truth_landmark_ecef is not None and "truth" in f:
                tg = f["truth"].create_group("matched")
                write_dataset(tg, "landmark_ecef", matched.truth_landmark_ecef, units="m", frame="ECEF")
                write_dataset(tg, "blunder", np.asarray(matched.truth_blunder, np.uint8))
            stamp_content_digest(f)
        os.chmod(tmp, file_mode())
        reseal(tmp)  # the whole-file SHA-256 of the edited copy, fsynced
        os.replace(tmp, path)
        fsync_directory(path.parent)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def _matched_group(f: Any, path: str | os.PathLike[str]) -> Any:
    """An open pass file's ``/matched`` group (FileFormatError if ``misrgraph match`` has not run)."""
    if "matched" not in f:
        raise FileFormatError(path, "no /matched group: run 'misrgraph match' on the scenario first")
    return f["matched"]


def _matched_summary(group: Any) -> dict[str, Any] | None:
    """The match summary stored on a ``/matched`` group (None if it has none)."""
    import json

    return json.loads(group.attrs["summary_json"]) if "summary_json" in group.attrs else None


def read_matched_summary(path: str | os.PathLike[str]) -> dict[str, Any] | None:
    """Only the match summary of a pass file's ``/matched`` group, without its observations
    (FileFormatError if ``misrgraph match`` has not run)."""
    with open_h5(path, "orbit_pass") as f:
        return _matched_summary(_matched_group(f, path))


def read_matched(path: str | os.PathLike[str], with_truth: bool = False) -> MatchedSet:
    """The matched observations of a pass file (FileFormatError if ``misrgraph match`` has not run)."""
    with open_h5(path, "orbit_pass") as f:
        m = _matched_group(f, path)
        lg, og = m["landmarks"], m["observations"]
        nl, no = lg["id"].shape[0], og["landmark"].shape[0]
        lms = Landmarks(*(read_dataset(lg, k, (nl,), dtype=np.int64) for k in ("id", "kind", "gcp_index")))
        obs = Observations(
            *(
                read_dataset(og, k, (no,), dtype=(np.int64 if k in ("landmark", "camera", "band") else float))
                for k in ("landmark", "camera", "band", "line", "sample", "exposure", "sigma_px")
            )
        )
        summary = _matched_summary(m)
        tl = tb = None
        if with_truth and "truth" in f and "matched" in f["truth"]:
            tg = f["truth"]["matched"]
            tl = read_dataset(tg, "landmark_ecef", (nl, 3))
            tb = read_dataset(tg, "blunder", (no,), dtype=bool)
        return MatchedSet(lms, obs, tl, tb, summary)
