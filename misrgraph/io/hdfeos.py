"""HDF-EOS2 grid files (HDF4), written and read through pyhdf without the HDF-EOS2 library.

An HDF-EOS2 grid file is an HDF4 file laid out by convention; this module writes that layout with
plain HDF4 calls, as the HDF-EOS2 library's ``GDcreate``/``GDdeffield``/``GDwriteattr`` do, so
that the library (and so GDAL's ``HDF4_EOS`` driver and the MISR Toolkit) reads the result:

* **Structural metadata.** The global attribute ``StructMetadata.0`` holds an ODL text
  describing every grid (:func:`struct_metadata`)::

      GROUP=GridStructure
        GROUP=GRID_1
          GridName="BlueBand"  XDim=512  YDim=2048
          UpperLeftPointMtrs=(x,y)  LowerRightMtrs=(x,y)     metres, projection plane
          Projection=GCTP_SOM  ProjParams=(13 GCTP numbers)  SphereCode=12
          GridOrigin=HDFE_GD_UL
          GROUP=Dimension  OBJECT=Dimension_1 DimensionName="SOMBlockDim" Size=180 ...
          GROUP=DataField  OBJECT=DataField_1 DataFieldName=... DataType=DFNT_UINT16
                           DimList=("SOMBlockDim","XDim","YDim") ...

  with ``HDFEOSVersion`` beside it. Parsed back by :func:`parse_odl`.
* **Fields** are SDSs named after the field, their dimensions named ``<dim>:<grid>``, their fill
  value set on the SDS. Each grid is a Vgroup named after it (class ``GRID``) holding a Vgroup
  ``Data Fields`` (class ``GRID Vgroup``) with the fields' SDSs and a Vgroup ``Grid Attributes``
  (class ``GRID Vgroup``).
* **Grid attributes** are one-record Vdatas (class ``Attr0.0``, one field ``AttrValues``) in the
  grid's ``Grid Attributes`` Vgroup; a field's fill value is also kept there as ``_FV_<field>``
  (what ``GDgetfillvalue`` reads) and a SOM grid's block offsets as ``_BLKSOM:<grid>`` (what
  ``GDblkSOMoffset`` reads).
* **File attributes** are SD global attributes; free Vdatas (e.g. per-block metadata tables) are
  written at the file's top level.

Writes are atomic (a hidden temporary in the target directory, renamed when complete, the mode
the umask allows); a file that is not HDF4, lacks the structural metadata or whose metadata names
a field the file does not hold is refused with a one-line :class:`~misrgraph.errors.FileFormatError`.
Fields of three or more dimensions are chunked one first-axis slice (one block) at a time and
compressed with deflate, through HDF4's ``SDsetchunk`` (pyhdf does not wrap it; it is called in
the HDF4 library pyhdf loaded), so that a field given for some blocks only stores those; where
that library cannot be reached, fields are written whole and compressed.
"""

from __future__ import annotations

import contextlib
import ctypes
import functools
import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator, Mapping, Sequence

import numpy as np
from numpy.typing import NDArray

from misrgraph.errors import FileFormatError, InputError, OutputError, require_extra
from misrgraph.io.h5 import atomic_path

__all__ = [
    "EosField",
    "EosGrid",
    "EosFile",
    "write_eos_file",
    "read_eos_file",
    "read_eos_field",
    "struct_metadata",
    "parse_odl",
    "HDFEOS_VERSION",
]

#: The version string written as the ``HDFEOSVersion`` file attribute.
HDFEOS_VERSION = "HDFEOS_V2.19"

#: numpy dtype -> HDF4 number type name (the ``DataType`` of the structural metadata).
_DFNT = {
    np.dtype(np.int8): "DFNT_INT8",
    np.dtype(np.uint8): "DFNT_UINT8",
    np.dtype(np.int16): "DFNT_INT16",
    np.dtype(np.uint16): "DFNT_UINT16",
    np.dtype(np.int32): "DFNT_INT32",
    np.dtype(np.uint32): "DFNT_UINT32",
    np.dtype(np.float32): "DFNT_FLOAT32",
    np.dtype(np.float64): "DFNT_FLOAT64",
}


def _pyhdf() -> tuple[Any, Any, Any, Any]:
    require_extra("pyhdf", "misr", "MISR's HDF-EOS2 files")
    import pyhdf.V  # noqa: F401  (HDF.vgstart needs it imported)
    import pyhdf.VS  # noqa: F401  (HDF.vstart needs it imported)
    from pyhdf.HDF import HC, HDF
    from pyhdf.SD import SD, SDC

    return SD, SDC, HDF, HC


class _ChunkDef(ctypes.Structure):
    """HDF4's ``HDF_CHUNK_DEF`` for chunking with compression: 32 chunk lengths, the compression
    type and model, then the compression parameters (deflate's level first; padded to cover the
    union's largest member)."""

    _fields_ = [
        ("lengths", ctypes.c_int32 * 32),
        ("comp_type", ctypes.c_int32),
        ("model_type", ctypes.c_int32),
        ("info", ctypes.c_int32 * 64),
    ]


_COMP_CODE_DEFLATE = 4
_HDF_CHUNK_AND_COMP = 0x3


@functools.lru_cache(maxsize=1)
def _sdsetchunk() -> Any:
    """HDF4's ``SDsetchunk`` from the mfhdf library pyhdf itself loaded (pyhdf does not wrap it);
    None where that library cannot be found, and fields are then written whole."""
    try:
        with open("/proc/self/maps") as fh:
            paths = {line.split()[-1] for line in fh if "libmfhdf" in line and line.rstrip().endswith((".so", ".0"))}
        for p in sorted(paths):
            lib = ctypes.CDLL(p)
            fn = lib.SDsetchunk
            fn.argtypes = [ctypes.c_int32, _ChunkDef, ctypes.c_int32]
            fn.restype = ctypes.c_int
            return fn
    except (OSError, AttributeError):
        return None
    return None


def _chunk_deflate(sds: Any, lengths: list[int], level: int) -> bool:
    """Make ``sds`` chunked (``lengths``) and deflate-compressed; False if not possible here."""
    fn = _sdsetchunk()
    if fn is None or len(lengths) > 32:
        return False
    cd = _ChunkDef()
    for i, n in enumerate(lengths):
        cd.lengths[i] = int(n)
    cd.comp_type = _COMP_CODE_DEFLATE
    cd.model_type = 0
    cd.info[0] = int(level)
    return fn(int(sds._id), cd, _HDF_CHUNK_AND_COMP) == 0


def _type_code(dtype: np.dtype, codes: Any) -> int:
    name = _DFNT.get(np.dtype(dtype))
    if name is None:
        raise InputError("dtype", str(dtype), ", ".join(str(d) for d in _DFNT))
    return int(getattr(codes, name.removeprefix("DFNT_")))


@dataclass(frozen=True)
class EosField:
    """One field of a grid: ``data`` with dimension names ``dims`` (``XDim``, ``YDim`` and the
    grid's extra dimensions), a fill value and SDS attributes (e.g. ``units``).

    ``index``: when given, ``data`` holds only these indices along the first dimension (e.g. the
    blocks a product covers, 0-based); the rest of the field is the fill value (which must then
    be given)."""

    name: str
    data: NDArray[Any]
    dims: tuple[str, ...]
    fill_value: float | int | None = None
    attrs: Mapping[str, Any] = field(default_factory=dict)
    index: Sequence[int] | None = None

    def __post_init__(self) -> None:
        if np.ndim(self.data) != len(self.dims):
            raise InputError(f"field {self.name}: dims", self.dims, f"{np.ndim(self.data)} dimension names")
        if np.dtype(self.data.dtype) not in _DFNT:
            raise InputError(f"field {self.name}: dtype", str(self.data.dtype), ", ".join(str(d) for d in _DFNT))
        if self.index is not None:
            if self.fill_value is None:
                raise InputError(f"field {self.name}: fill_value", None, "a fill value for the indices not given")
            if len(self.index) != np.shape(self.data)[0]:
                raise InputError(f"field {self.name}: index", len(self.index), f"{np.shape(self.data)[0]} indices")


@dataclass(frozen=True)
class EosGrid:
    """One HDF-EOS2 grid: its size (``xdim`` x ``ydim``), corners (m), GCTP projection, extra
    dimensions, fields and grid attributes (numbers, arrays or strings)."""

    name: str
    xdim: int
    ydim: int
    upper_left_m: tuple[float, float]
    lower_right_m: tuple[float, float]
    projection: str
    proj_params: tuple[float, ...]
    sphere_code: int
    dimensions: Mapping[str, int]
    fields: Sequence[EosField]
    attributes: Mapping[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        sizes = {"XDim": self.xdim, "YDim": self.ydim, **dict(self.dimensions)}
        for f in self.fields:
            for k, (d, n) in enumerate(zip(f.dims, np.shape(f.data))):
                if d not in sizes:
                    raise InputError(f"grid {self.name}: field {f.name} dimension", d, sorted(sizes))
                if f.index is not None and k == 0:
                    bad = [i for i in f.index if not 0 <= int(i) < sizes[d]]
                    if bad:
                        raise InputError(f"grid {self.name}: field {f.name} index", bad[0], f"0..{sizes[d] - 1}")
                    continue
                if sizes[d] != n:
                    raise InputError(f"grid {self.name}: field {f.name} size along {d}", n, f"{sizes[d]}")


@dataclass(frozen=True)
class EosFile:
    """What :func:`read_eos_file` finds: file attributes, the parsed structural metadata per grid,
    each grid's attributes and the top-level Vdatas (name -> {field: values})."""

    path: Path
    attributes: dict[str, Any]
    grids: dict[str, dict[str, Any]]
    grid_attributes: dict[str, dict[str, Any]]
    vdatas: dict[str, dict[str, Any]]


def _fmt(v: float) -> str:
    """A number as the structural metadata spells it (no exponent for whole numbers)."""
    v = float(v)
    return str(int(v)) if v == int(v) and abs(v) < 1e15 else repr(v)


def struct_metadata(grids: Sequence[EosGrid]) -> str:
    """The ODL text of ``StructMetadata.0`` for ``grids`` (the layout of the module docstring)."""
    out = ["GROUP=SwathStructure", "END_GROUP=SwathStructure", "GROUP=GridStructure"]
    for i, g in enumerate(grids, 1):
        out += [
            f"\tGROUP=GRID_{i}",
            f'\t\tGridName="{g.name}"',
            f"\t\tXDim={int(g.xdim)}",
            f"\t\tYDim={int(g.ydim)}",
            "\t\tUpperLeftPointMtrs=({:.6f},{:.6f})".format(*g.upper_left_m),
            "\t\tLowerRightMtrs=({:.6f},{:.6f})".format(*g.lower_right_m),
            f"\t\tProjection={g.projection}",
            "\t\tProjParams=(" + ",".join(_fmt(p) for p in g.proj_params) + ")",
            f"\t\tSphereCode={int(g.sphere_code)}",
            "\t\tGridOrigin=HDFE_GD_UL",
            "\t\tGROUP=Dimension",
        ]
        for j, (d, n) in enumerate(g.dimensions.items(), 1):
            out += [
                f"\t\t\tOBJECT=Dimension_{j}",
                f'\t\t\t\tDimensionName="{d}"',
                f"\t\t\t\tSize={int(n)}",
                f"\t\t\tEND_OBJECT=Dimension_{j}",
            ]
        out += ["\t\tEND_GROUP=Dimension", "\t\tGROUP=DataField"]
        for j, f in enumerate(g.fields, 1):
            dims = ",".join(f'"{d}"' for d in f.dims)
            out += [
                f"\t\t\tOBJECT=DataField_{j}",
                f'\t\t\t\tDataFieldName="{f.name}"',
                f"\t\t\t\tDataType={_DFNT[np.dtype(f.data.dtype)]}",
                f"\t\t\t\tDimList=({dims})",
                f"\t\t\tEND_OBJECT=DataField_{j}",
            ]
        out += [
            "\t\tEND_GROUP=DataField",
            "\t\tGROUP=MergedFields",
            "\t\tEND_GROUP=MergedFields",
            f"\tEND_GROUP=GRID_{i}",
        ]
    out += ["END_GROUP=GridStructure", "GROUP=PointStructure", "END_GROUP=PointStructure", "END", ""]
    return "\n".join(out)


_ODL_LINE = re.compile(r"^\s*([A-Za-z_][\w.]*)\s*=\s*(.*?)\s*$")


def _odl_value(text: str) -> Any:
    text = text.strip()
    if text.startswith("(") and text.endswith(")"):
        inner = text[1:-1]
        return tuple(_odl_value(p) for p in re.findall(r'"[^"]*"|[^,]+', inner))
    if text.startswith('"') and text.endswith('"'):
        return text[1:-1]
    try:
        return int(text)
    except ValueError:
        pass
    try:
        return float(text)
    except ValueError:
        return text


def parse_odl(text: str) -> dict[str, Any]:
    """Parse ODL (``GROUP``/``OBJECT`` blocks of ``KEY=VALUE`` lines) into nested dicts; a group or
    object becomes a dict under its name, values become str, int, float or tuples of them.

    Raises :class:`InputError` on an unbalanced ``END_GROUP``/``END_OBJECT``."""
    root: dict[str, Any] = {}
    stack: list[tuple[str, dict[str, Any]]] = [("", root)]
    for raw in text.replace("\x00", "").splitlines():
        m = _ODL_LINE.match(raw)
        if not m:
            if raw.strip() not in ("", "END"):
                raise InputError("ODL line", raw.strip()[:60], "KEY=VALUE, GROUP=, OBJECT=, END_GROUP=, END_OBJECT=")
            continue
        key, value = m.group(1), m.group(2)
        if key in ("GROUP", "OBJECT"):
            node: dict[str, Any] = {}
            stack[-1][1][value] = node
            stack.append((value, node))
        elif key in ("END_GROUP", "END_OBJECT"):
            if len(stack) == 1 or stack[-1][0] != value:
                raise InputError(f"ODL {key}", value, f"the open {stack[-1][0] or 'nothing'}")
            stack.pop()
        else:
            stack[-1][1][key] = _odl_value(value)
    if len(stack) != 1:
        raise InputError("ODL", stack[-1][0], "every GROUP and OBJECT closed")
    return root


def _set_sd_attr(obj: Any, name: str, value: Any, SDC: Any) -> None:
    a = obj.attr(name)
    if isinstance(value, str):
        a.set(SDC.CHAR8, value)
        return
    arr = np.atleast_1d(np.asarray(value))
    if arr.dtype == np.bool_:
        arr = arr.astype(np.int32)
    if arr.dtype.kind == "f":
        arr = arr.astype(np.float64) if arr.dtype != np.float32 else arr
    elif arr.dtype.kind in "iu" and arr.dtype not in _DFNT:  # int64 and kin: HDF4 attributes hold int32
        arr = arr.astype(np.int32)
    values = arr.tolist()
    a.set(_type_code(arr.dtype, SDC), values[0] if len(values) == 1 else values)


def _write_vdata(vs: Any, HC: Any, name: str, klass: str, columns: Mapping[str, Any]) -> Any:
    """A Vdata of one record per row (each column one field; a string column is CHAR8)."""
    defs, cols = [], []
    n_rows = None
    for fname, col in columns.items():
        if isinstance(col, str):
            defs.append((fname, HC.CHAR8, max(len(col), 1)))
            cols.append([col])
            rows = 1
        else:
            arr = np.asarray(col)
            if arr.dtype == np.int64:
                arr = arr.astype(np.int32)
            if arr.dtype == np.bool_:
                arr = arr.astype(np.uint8)
            arr2 = arr.reshape(arr.shape[0], -1) if arr.ndim else arr.reshape(1, 1)
            order = int(arr2.shape[1])
            defs.append((fname, _type_code(arr2.dtype, HC), order))
            cols.append([row[0] if order == 1 else row for row in arr2.tolist()])
            rows = arr2.shape[0]
        if n_rows is not None and rows != n_rows:
            raise InputError(f"vdata {name}: rows of {fname}", rows, f"{n_rows}")
        n_rows = rows
    vd = vs.create(name, defs)
    vd._class = klass
    vd.write([[c[i] for c in cols] for i in range(n_rows or 0)])
    return vd


def _attr_columns(value: Any) -> dict[str, Any]:
    if isinstance(value, str):
        return {"AttrValues": value}
    arr = np.atleast_1d(np.asarray(value))
    if arr.dtype.kind == "f" and arr.dtype != np.float32:
        arr = arr.astype(np.float64)
    return {"AttrValues": arr.reshape(1, -1)}


@contextlib.contextmanager
def _temporary(target: Path) -> Iterator[str]:
    """:func:`~misrgraph.io.h5.atomic_path`, with pyhdf's errors as one-line output errors."""
    with atomic_path(target) as tmp:
        try:
            yield tmp
        except Exception as exc:
            if type(exc).__module__.startswith("pyhdf"):
                raise OutputError(target, f"HDF4 write failed ({exc})") from exc
            raise


def write_eos_file(
    path: str | os.PathLike[str],
    grids: Sequence[EosGrid],
    attributes: Mapping[str, Any] | None = None,
    vdatas: Mapping[str, tuple[str, Mapping[str, Any]]] | None = None,
    deflate_level: int = 1,
) -> Path:
    """Write an HDF-EOS2 grid file atomically.

    Parameters
    ----------
    path : path-like
        The file to write; it appears only when complete.
    grids : sequence of EosGrid
        The grids, in order (``GRID_1``, ``GRID_2``, ...).
    attributes : mapping, optional
        File (SD global) attributes: str, numbers or 1-D arrays.
    vdatas : mapping, optional
        Top-level Vdatas: name -> (class, {field: column}); a column is 1-D (one value per record),
        2-D (an order > 1 field) or a str.
    deflate_level : int
        Deflate level (1..9) of every field.

    Returns
    -------
    pathlib.Path
        ``path``.
    """
    SD, SDC, HDF, HC = _pyhdf()
    target = Path(path)
    names = [g.name for g in grids]
    if len(set(names)) != len(names):
        raise InputError("grid names", names, "distinct names")
    with _temporary(target) as tmp:
        sd = SD(tmp, SDC.WRITE | SDC.CREATE | SDC.TRUNC)
        refs: dict[str, list[int]] = {}
        try:
            _set_sd_attr(sd, "HDFEOSVersion", HDFEOS_VERSION, SDC)
            _set_sd_attr(sd, "StructMetadata.0", struct_metadata(grids), SDC)
            for k, v in (attributes or {}).items():
                _set_sd_attr(sd, k, v, SDC)
            for g in grids:
                refs[g.name] = []
                sizes = {"XDim": g.xdim, "YDim": g.ydim, **dict(g.dimensions)}
                for f in g.fields:
                    data = np.ascontiguousarray(f.data)
                    shape = [sizes[d] for d in f.dims]
                    sds = sd.create(f.name, _type_code(data.dtype, SDC), shape)
                    for i, d in enumerate(f.dims):
                        sds.dim(i).setname(f"{d}:{g.name}")
                    if f.fill_value is not None:
                        sds.setfillvalue(np.asarray(f.fill_value, dtype=data.dtype).item())
                    for k, v in f.attrs.items():
                        _set_sd_attr(sds, k, v, SDC)
                    chunked = _chunk_deflate(sds, [1, *shape[1:]], int(deflate_level)) if len(shape) > 2 else False
                    if not chunked:
                        sds.setcompress(SDC.COMP_DEFLATE, int(deflate_level))
                    if f.index is None:
                        sds[:] = data
                    elif chunked:  # only the chunks that hold data are stored
                        for k, i in enumerate(f.index):
                            sds[int(i)] = data[k]
                    else:
                        full = np.full(shape, f.fill_value, dtype=data.dtype)
                        full[np.asarray(f.index, dtype=np.int64)] = data
                        sds[:] = full
                    refs[g.name].append(sds.ref())
                    sds.endaccess()
        finally:
            sd.end()
        hdf = HDF(tmp, HC.WRITE)
        v, vs = hdf.vgstart(), hdf.vstart()
        try:
            for g in grids:
                grid_vg = v.create(g.name)
                grid_vg._class = "GRID"
                fields_vg = v.create("Data Fields")
                fields_vg._class = "GRID Vgroup"
                grid_vg.insert(fields_vg)
                attrs_vg = v.create("Grid Attributes")
                attrs_vg._class = "GRID Vgroup"
                grid_vg.insert(attrs_vg)
                for ref in refs[g.name]:
                    fields_vg.add(HC.DFTAG_NDG, ref)
                grid_attrs = dict(g.attributes)
                for f in g.fields:
                    if f.fill_value is not None:
                        grid_attrs[f"_FV_{f.name}"] = np.asarray([f.fill_value], dtype=f.data.dtype)
                for name, value in grid_attrs.items():
                    vd = _write_vdata(vs, HC, name, "Attr0.0", _attr_columns(value))
                    attrs_vg.insert(vd)
                    vd.detach()
                for vg in (attrs_vg, fields_vg, grid_vg):
                    vg.detach()
            for name, (klass, columns) in (vdatas or {}).items():
                _write_vdata(vs, HC, name, klass, columns).detach()
        finally:
            vs.end()
            v.end()
            hdf.close()
    return target


def _open_error(path: Path, exc: Exception) -> FileFormatError:
    return FileFormatError(path, f"not a readable HDF4 file ({str(exc).strip() or type(exc).__name__})")


def read_eos_file(path: str | os.PathLike[str]) -> EosFile:
    """Read an HDF-EOS2 grid file's structure: file attributes, the structural metadata of every
    grid (checked against the SDSs the file holds), grid attributes and top-level Vdatas.
    Field data: :func:`read_eos_field`."""
    SD, SDC, HDF, HC = _pyhdf()
    p = Path(path)
    if not p.is_file():
        raise FileFormatError(p, "no such file")
    try:
        sd = SD(str(p), SDC.READ)
    except Exception as exc:  # pyhdf raises HDF4Error for anything it cannot open
        raise _open_error(p, exc) from None
    try:
        attrs = {k: v for k, v in sd.attributes().items()}
        datasets = set(sd.datasets())
    finally:
        sd.end()
    text = "".join(str(attrs[k]) for k in sorted(a for a in attrs if a.startswith("StructMetadata.")))
    if not text:
        raise FileFormatError(p, "no StructMetadata.0 attribute: not an HDF-EOS2 file")
    try:
        odl = parse_odl(text)
    except InputError as exc:
        raise FileFormatError(p, f"StructMetadata.0 is not valid ODL ({exc})") from None
    grids = {}
    for g in odl.get("GridStructure", {}).values():
        if not isinstance(g, dict) or "GridName" not in g:
            continue
        fields = {f["DataFieldName"]: f for f in g.get("DataField", {}).values() if isinstance(f, dict)}
        missing = [f for f in fields if f not in datasets]
        if missing:
            raise FileFormatError(p, f"grid {g['GridName']}: field {missing[0]} is in the metadata but not in the file")
        dims = {d["DimensionName"]: int(d["Size"]) for d in g.get("Dimension", {}).values() if isinstance(d, dict)}
        grids[str(g["GridName"])] = {**g, "fields": fields, "dimensions": dims}
    grid_attrs: dict[str, dict[str, Any]] = {name: {} for name in grids}
    vdatas: dict[str, dict[str, Any]] = {}
    try:
        hdf = HDF(str(p), HC.READ)
    except Exception as exc:
        raise _open_error(p, exc) from None
    v, vs = hdf.vgstart(), hdf.vstart()
    try:
        in_grids: set[int] = set()
        ref = _next_vgroup(v, -1)
        while ref is not None:
            vg = v.attach(ref)
            if vg._class == "GRID" and vg._name in grids:
                for tag, r in vg.tagrefs():
                    sub = v.attach(r) if tag == HC.DFTAG_VG else None
                    if sub is not None and sub._name == "Grid Attributes":
                        for tag2, r2 in sub.tagrefs():
                            if tag2 == HC.DFTAG_VH:
                                in_grids.add(r2)
                                vd = vs.attach(r2)
                                vals = vd.read(vd._nrecs)
                                grid_attrs[vg._name][vd._name] = _attr_value(vals)
                                vd.detach()
                    if sub is not None:
                        sub.detach()
            vg.detach()
            ref = _next_vgroup(v, ref)
        ref = _next_vdata(vs, -1)
        while ref is not None:
            vd = vs.attach(ref)
            if ref not in in_grids and not vd._isattr and not str(vd._class).startswith(_HDF_INTERNAL_VDATA):
                fields = vd._fields
                recs = vd.read(vd._nrecs) if vd._nrecs else []
                vdatas[vd._name] = {
                    f: np.asarray([r[i] for r in recs]).squeeze() if recs else np.empty(0) for i, f in enumerate(fields)
                }
            vd.detach()
            ref = _next_vdata(vs, ref)
    finally:
        vs.end()
        v.end()
        hdf.close()
    for g in grids:
        if not grid_attrs[g] and g not in _grid_vgroups(p):
            raise FileFormatError(p, f"grid {g} has no Vgroup of class GRID")
    return EosFile(p, attrs, grids, grid_attrs, vdatas)


#: Vdata classes the HDF4 library writes for its own use (dimension scales, attributes).
_HDF_INTERNAL_VDATA = ("DimVal", "Var0", "Attr0", "_HDF")


def _next_vgroup(v: Any, ref: int) -> int | None:
    try:
        nxt = int(v.getid(ref))
    except Exception:  # pyhdf raises HDF4Error past the last Vgroup
        return None
    return None if nxt == -1 else nxt


def _next_vdata(vs: Any, ref: int) -> int | None:
    try:
        return int(vs.next(ref))
    except Exception:  # pyhdf raises HDF4Error past the last Vdata
        return None


def _grid_vgroups(p: Path) -> set[str]:
    _, _, HDF, HC = _pyhdf()
    hdf = HDF(str(p), HC.READ)
    v = hdf.vgstart()
    out = set()
    try:
        ref = _next_vgroup(v, -1)
        while ref is not None:
            vg = v.attach(ref)
            if vg._class == "GRID":
                out.add(vg._name)
            vg.detach()
            ref = _next_vgroup(v, ref)
    finally:
        v.end()
        hdf.close()
    return out


def _attr_value(records: list[Any]) -> Any:
    if not records:
        return None
    value = records[0][0]
    if isinstance(value, str):
        return value
    arr = np.asarray(value)
    return arr.item() if arr.size == 1 else arr


def read_eos_field(path: str | os.PathLike[str], name: str, blocks: Sequence[int] | None = None) -> NDArray[Any]:
    """The data of field ``name`` (the whole SDS, or its first-axis indices ``blocks``)."""
    SD, SDC, _, _ = _pyhdf()
    p = Path(path)
    try:
        sd = SD(str(p), SDC.READ)
    except Exception as exc:
        raise _open_error(p, exc) from None
    try:
        if name not in sd.datasets():
            raise FileFormatError(p, f"no field {name!r}")
        sds = sd.select(name)
        try:
            if blocks is None:
                return np.asarray(sds[:])
            return np.stack([np.asarray(sds[int(b)]) for b in blocks])
        finally:
            sds.endaccess()
    finally:
        sd.end()
