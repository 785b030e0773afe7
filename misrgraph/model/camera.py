"""The Camera Geometric Model (CGM) of eq. 2 for the nine MISR cameras and four bands.

``r_scs = T_si @ T_ic @ T_cd @ [-(k + (l - INT(l + 0.5)) dx), f * sum_i alpha_i (s - c_y)^i, f]``

with ``T_si = Rz(wz) Ry(wy) Rx(wx)`` (instrument -> spacecraft, common to all cameras),
``T_ic = Ry(beta) Rx(delta)`` (camera -> instrument, active rotations: delta first rolls the
camera about its along-track line axis, beta then tilts it fore/aft, positive forward; the
boresight's cross-track component is ``-sin(delta)`` whatever beta is, which is how MISR's
delta compensates Earth rotation) and ``T_cd = Rz(eps)`` (detector -> camera, about the boresight).
Axes: x along track (forward), y right of the flight direction, z nadir. Units: radians, metres, pixels. ``alpha_i``
is in pixel^-i, so that ``f * alpha_1 = 21 um`` is the cross-track pitch and ``f * sum alpha_i (s - c_y)^i`` is the
cross-track focal-plane coordinate in metres.

The parameters are data: :class:`CameraModel` is a dataclass; :mod:`misrgraph.io.camera` reads and
writes it as HDF5 (kind ``camera_model``). Camera arrays are indexed in the order of
:data:`misrgraph.model.constants.CAMERAS`, band arrays in the order of :data:`~misrgraph.model.constants.BANDS`.
A model tabulated at several temperatures is a :class:`TabulatedCameraModel`, whose
``at_temperature`` interpolates linearly; a plain model's ``at_temperature`` returns itself.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from factors.geometry import detector_vector, rot_x, rot_y, rot_z
from misrgraph.errors import InputError
from misrgraph.model.constants import BANDS, CAMERAS, LINE_TIME_S, N_PIXELS, PITCH_ALONG_M, PITCH_CROSS_M

__all__ = [
    "CameraModel",
    "TabulatedCameraModel",
    "N_ALPHA",
    "BAND_ANGLE_DEG",
    "validate_pixel_inputs",
    "sample_direction",
]

Array = NDArray[np.float64]
N_ALPHA = 6
NC, NB = len(CAMERAS), len(BANDS)

#: Nominal along-track angle of each band's line array from the optical axis (deg, detector
#: frame, positive toward -x_detector i.e. k > 0). Red matches Table 1's An value (-0.050 deg);
#: the arrays are equally spaced by 0.075 deg.
BAND_ANGLE_DEG: dict[str, float] = {"blue": 0.100, "green": 0.025, "red": -0.050, "nir": -0.125}


@dataclass
class CameraModel:
    """Parameters of eq. 2 for all cameras and bands (SI units, radians).

    Shapes: ``omega (3,)`` as (wx, wy, wz); ``delta, beta, epsilon (9,)``;
    ``focal_length, k, cy (9, 4)``; ``alpha (9, 4, 6)``; ``band_delta, band_beta, band_epsilon
    (9, 4)``: each band's own angle offsets (rad), added to the camera's angles for that band's
    line array (zero unless a per-band calibration or truth sets them; see :meth:`angles`).
    ``dx``/``dy`` are the along/cross-track detector pitches (m); ``line_time`` the line repeat
    time (s); ``temperature_c`` the temperature (deg C) at which the parameters hold.
    """

    omega: Array
    delta: Array
    beta: Array
    epsilon: Array
    focal_length: Array
    alpha: Array
    k: Array
    cy: Array
    dx: float = PITCH_ALONG_M
    dy: float = PITCH_CROSS_M
    line_time: float = LINE_TIME_S
    temperature_c: float = 5.0
    provenance: dict[str, str] = field(default_factory=dict)
    band_delta: Array = field(default_factory=lambda: np.zeros((NC, NB)))
    band_beta: Array = field(default_factory=lambda: np.zeros((NC, NB)))
    band_epsilon: Array = field(default_factory=lambda: np.zeros((NC, NB)))

    _SHAPES = {
        "omega": (3,),
        "delta": (NC,),
        "beta": (NC,),
        "epsilon": (NC,),
        "focal_length": (NC, NB),
        "alpha": (NC, NB, N_ALPHA),
        "k": (NC, NB),
        "cy": (NC, NB),
        "band_delta": (NC, NB),
        "band_beta": (NC, NB),
        "band_epsilon": (NC, NB),
    }

    def __post_init__(self) -> None:
        for name, shape in self._SHAPES.items():
            arr = np.asarray(getattr(self, name), dtype=float)
            if arr.shape != shape:
                raise InputError(f"CameraModel.{name}", arr.shape, f"shape {shape}")
            if not np.all(np.isfinite(arr)):
                raise InputError(f"CameraModel.{name}", "non-finite values", "finite numbers")
            setattr(self, name, arr)
        if np.any(self.focal_length <= 0):
            raise InputError("CameraModel.focal_length", self.focal_length.min(), "positive metres")

    # ------------------------------------------------------------------ construction
    def copy(self) -> "CameraModel":
        """Deep copy."""
        return dataclasses.replace(
            self, **{n: np.array(getattr(self, n)) for n in self._SHAPES}, provenance=dict(self.provenance)
        )

    def add_correction(self, param: str, camera: int, band: int | None, value: float) -> None:
        """Add one estimated correction in place: ``param`` is ``delta``, ``beta``, ``epsilon``
        (rad), ``f`` (m) or ``alpha0``..``alpha5`` (pixel^-i). A per-band angle correction
        (``band`` given) goes into that band's offset (``band_delta`` ...), never into the
        camera-level angle the bands share; a camera-level ``f`` or ``alpha`` correction
        (``band=None``) applies to every band. The one place corrections meet a model: the
        adjustment, the calibration and their scoring all go through it."""
        b = slice(None) if band is None else band
        if param in ("delta", "beta", "epsilon"):
            if band is None:
                getattr(self, param)[camera] += value
            else:
                getattr(self, "band_" + param)[camera, band] += value
        elif param == "f":
            self.focal_length[camera, b] += value
        elif param.startswith("alpha") and param[5:].isdigit() and int(param[5:]) < N_ALPHA:
            self.alpha[camera, b, int(param[5:])] += value
        else:
            raise InputError("camera parameter", param, "delta, beta, epsilon, f or alpha0..alpha5")

    def corrected(
        self,
        corrections: "dict[int, ArrayLike]",
        params: tuple[str, ...] = ("delta", "beta", "epsilon"),
        sign: float = 1.0,
    ) -> "CameraModel":
        """A copy with camera-level corrections added (``sign=-1``: removed): ``corrections`` maps a
        camera index to its values in the order of ``params``."""
        m = self.copy()
        for c, values in corrections.items():
            for p, v in zip(params, np.asarray(values, dtype=float)):
                m.add_correction(p, int(c), None, sign * float(v))
        return m

    # ------------------------------------------------------------------ geometry
    def t_si(self) -> Array:
        """Instrument -> spacecraft rotation ``Rz(wz) Ry(wy) Rx(wx)``, (3, 3)."""
        wx, wy, wz = self.omega
        return rot_z(wz) @ rot_y(wy) @ rot_x(wx)

    def angles(self, cam: ArrayLike, band: ArrayLike | None = None) -> tuple[Array, Array, Array]:
        """(delta, beta, epsilon) in rad of cameras, plus each band's offsets when ``band`` is given."""
        c = np.asarray(cam, dtype=int)
        if band is None:
            return self.delta[c], self.beta[c], self.epsilon[c]
        b = np.asarray(band, dtype=int)
        return (
            self.delta[c] + self.band_delta[c, b],
            self.beta[c] + self.band_beta[c, b],
            self.epsilon[c] + self.band_epsilon[c, b],
        )

    def t_ic(self, cam: ArrayLike, band: ArrayLike | None = None) -> Array:
        """Camera -> instrument rotation ``Ry(beta) Rx(delta)`` for camera (and band) indices, (..., 3, 3)."""
        d, b_, _ = self.angles(cam, band)
        return rot_y(b_) @ rot_x(d)

    def t_cd(self, cam: ArrayLike, band: ArrayLike | None = None) -> Array:
        """Detector -> camera rotation ``Rz(eps)``, (..., 3, 3)."""
        return rot_z(self.angles(cam, band)[2])

    def detector_to_spacecraft(self, cam: ArrayLike, band: ArrayLike | None = None) -> Array:
        """``T_si T_ic T_cd`` for camera (and band) indices, (..., 3, 3); without ``band`` the
        camera-level angles (no band offsets)."""
        c = np.asarray(cam, dtype=int)
        b = None if band is None else np.asarray(band, dtype=int)
        if (
            c.ndim
            and c.size > 1
            and np.all(c == c.flat[0])
            and (b is None or (b.shape == c.shape and np.all(b == b.flat[0])))
        ):
            # one camera/band for all (the common case): one matrix, broadcast
            one = self.detector_to_spacecraft(int(c.flat[0]), None if b is None else int(b.flat[0]))
            return np.broadcast_to(one, c.shape + (3, 3))
        return self.t_si() @ self.t_ic(cam, band) @ self.t_cd(cam, band)

    def detector_vectors(
        self, cam: ArrayLike, band: ArrayLike, line: ArrayLike, sample: ArrayLike, exposure: ArrayLike | None = None
    ) -> Array:
        """Eq. 2 detector-frame vectors (m) for index arrays, (..., 3).

        The along-track fraction is ``line - exposure`` with ``exposure = INT(line + 0.5)`` unless
        given (see :class:`misrgraph.model.geolocation.ImagePoints`)."""
        c = np.asarray(cam, dtype=int)
        b = np.asarray(band, dtype=int)
        return detector_vector(
            line, sample, self.k[c, b], self.dx, self.focal_length[c, b], self.alpha[c, b], self.cy[c, b], exposure
        )

    def direction_scs(
        self, cam: ArrayLike, band: ArrayLike, line: ArrayLike, sample: ArrayLike, exposure: ArrayLike | None = None
    ) -> Array:
        """Unit pointing vectors in the spacecraft frame for pixels, (..., 3) (eq. 2)."""
        d = self.detector_vectors(cam, band, line, sample, exposure)
        r = np.einsum("...ij,...j->...i", self.detector_to_spacecraft(cam, band), d)
        return r / np.linalg.norm(r, axis=-1, keepdims=True)

    def focal_plane_y(self, cam: ArrayLike, band: ArrayLike, sample: ArrayLike) -> Array:
        """Cross-track focal-plane coordinate ``f sum alpha_i (s - c_y)^i`` (m)."""
        c, b = np.asarray(cam, dtype=int), np.asarray(band, dtype=int)
        s = np.asarray(sample, dtype=float) - self.cy[c, b]
        a = self.alpha[c, b]
        acc = a[..., N_ALPHA - 1] * np.ones_like(s)
        for i in range(N_ALPHA - 2, -1, -1):  # Horner
            acc = acc * s + a[..., i]
        return self.focal_length[c, b] * acc

    def focal_plane_dy_ds(self, cam: ArrayLike, band: ArrayLike, sample: ArrayLike) -> Array:
        """Derivative of :meth:`focal_plane_y` with respect to the sample (m per pixel)."""
        c, b = np.asarray(cam, dtype=int), np.asarray(band, dtype=int)
        s = np.asarray(sample, dtype=float) - self.cy[c, b]
        a = self.alpha[c, b]
        acc = (N_ALPHA - 1) * a[..., N_ALPHA - 1] * np.ones_like(s)
        for i in range(N_ALPHA - 2, 0, -1):  # Horner on sum i alpha_i s^(i-1)
            acc = acc * s + i * a[..., i]
        return self.focal_length[c, b] * acc

    def sample_from_focal_plane_y(self, cam: ArrayLike, band: ArrayLike, y: ArrayLike, iterations: int = 8) -> Array:
        """Invert :meth:`focal_plane_y` by Newton's method (the polynomial is monotonic on the swath)."""
        c, b = np.asarray(cam, dtype=int), np.asarray(band, dtype=int)
        y = np.asarray(y, dtype=float)
        s = self.cy[c, b] + y / (self.focal_length[c, b] * self.alpha[c, b, 1])
        for _ in range(iterations):
            s = s - (self.focal_plane_y(c, b, s) - y) / self.focal_plane_dy_ds(c, b, s)
        return s

    def ifov_cross_rad(self, cam: ArrayLike, band: ArrayLike, sample: ArrayLike) -> Array:
        """Cross-track angular size of one pixel (rad, positive whichever way the samples run) at a sample."""
        c, b = np.asarray(cam, dtype=int), np.asarray(band, dtype=int)
        y = self.focal_plane_y(c, b, sample)
        f = self.focal_length[c, b]
        return np.abs(self.focal_plane_dy_ds(c, b, sample)) * f / (f * f + y * y)

    # ------------------------------------------------------------------ temperature
    def at_temperature(self, temperature_c: float) -> "CameraModel":
        """This model (single temperature) unchanged; tabulated models override (see TabulatedCameraModel)."""
        return self


def sample_direction(camera: CameraModel, cam: ArrayLike, band: ArrayLike) -> Array:
    """+1 where the cross-track focal-plane coordinate grows with the sample number, -1 where it
    falls (the sign of ``dy/ds`` at the boresight; see :data:`misrgraph.model.constants.SAMPLE_DIRECTION`)."""
    c, b = np.asarray(cam, dtype=int), np.asarray(band, dtype=int)
    return np.sign(camera.focal_plane_dy_ds(c, b, camera.cy[c, b])).astype(int)


def validate_pixel_inputs(camera: str, band: str, sample: float | None = None) -> tuple[int, int]:
    """Validate a (camera, band, sample) triple from a user; return indices or raise InputError."""
    from misrgraph.model.constants import band_index, camera_index

    c = camera_index(camera)
    b = band_index(band)
    if sample is not None and not (0 <= float(sample) <= N_PIXELS - 1):
        raise InputError("pixel", sample, f"a sample number in 0..{N_PIXELS - 1}")
    return c, b


class TabulatedCameraModel:
    """A camera model tabulated at several temperatures, piecewise linear in temperature.

    The seed's parameters are thermally sensitive (Table 1: f and alpha measured at three
    temperatures; delta, beta thermal). ``at_temperature(T)`` interpolates every parameter array
    linearly between the two nearest tabulated temperatures and returns a plain
    :class:`CameraModel`. Outside the tabulated temperatures the end segments are extended
    linearly up to ``valid_range_c`` (deg C; default: the tabulated range, i.e. clamping), and the
    temperature is clamped beyond it. Calibration and adjustment use the model at each pass's
    temperature. Saved as a ``camera_model`` file whose ``/camera_model`` group is the model at
    the first temperature plus a ``/temperature_table/<i>`` group per tabulated temperature (attr
    ``valid_range_c``).
    """

    def __init__(self, models: list[CameraModel], valid_range_c: tuple[float, float] | None = None) -> None:
        if len(models) < 2:
            raise InputError("temperature table", len(models), "at least two models at different temperatures")
        temps = np.array([m.temperature_c for m in models])
        order = np.argsort(temps)
        if np.any(np.diff(temps[order]) <= 0):
            raise InputError("temperature table", temps.tolist(), "distinct temperatures")
        self.models = [models[i] for i in order]
        self.temperatures_c = temps[order]
        lo, hi = (
            (float(self.temperatures_c[0]), float(self.temperatures_c[-1])) if valid_range_c is None else valid_range_c
        )
        if not (np.isfinite(lo) and np.isfinite(hi) and lo <= self.temperatures_c[0] and hi >= self.temperatures_c[-1]):
            raise InputError("valid_range_c", (lo, hi), "finite (low, high) that contains the tabulated temperatures")
        self.valid_range_c = (float(lo), float(hi))

    @classmethod
    def linear(
        cls, base: CameraModel, slopes: dict[str, Array], t_range_c: tuple[float, float]
    ) -> "TabulatedCameraModel":
        """A model linear in temperature: ``base`` holds at ``base.temperature_c``; ``slopes`` per deg C,
        each of shape (9,): ``delta``, ``beta`` (rad/C) and ``focal_scale`` (1/C, the relative
        change of f with the focal-plane polynomial ``f alpha_i`` fixed, i.e. every alpha_i / (1 + x)).
        Tabulated at the two ends of ``t_range_c``, so it is exact in between."""
        unknown = set(slopes) - {"delta", "beta", "focal_scale"}
        if unknown:
            raise InputError("slopes", sorted(unknown), "keys from delta, beta, focal_scale")
        models = []
        for t in t_range_c:
            m = base.copy()
            dt = float(t) - base.temperature_c
            for name in ("delta", "beta"):
                if name in slopes:
                    getattr(m, name)[:] += np.asarray(slopes[name], float) * dt
            if "focal_scale" in slopes:
                x = 1.0 + np.asarray(slopes["focal_scale"], float) * dt
                m.focal_length *= x[:, None]
                m.alpha /= x[:, None, None]
            m.temperature_c = float(t)
            models.append(m)
        return cls(models)

    @property
    def line_time(self) -> float:
        return self.models[0].line_time

    def at_temperature(self, temperature_c: float) -> CameraModel:
        t = float(np.clip(temperature_c, *self.valid_range_c))
        i = int(np.clip(np.searchsorted(self.temperatures_c, t) - 1, 0, len(self.models) - 2))
        a, b = self.models[i], self.models[i + 1]
        w = (t - self.temperatures_c[i]) / (self.temperatures_c[i + 1] - self.temperatures_c[i])
        out = a.copy()
        for name in CameraModel._SHAPES:
            setattr(out, name, (1 - w) * getattr(a, name) + w * getattr(b, name))
        out.temperature_c = t
        out.provenance = dict(a.provenance, interpolated_at_c=f"{t:.3f}")
        return out
