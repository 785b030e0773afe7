"""Noise-model files: the levels of :class:`misrgraph.model.noise.NoiseModel` as JSON.

Layout (UTF-8 JSON, written atomically)::

    {"kind": "misrgraph noise model", "version": 1,
     "attitude": {"value_sigma_arcsec": [r, p, y], "rate_sigma_arcsec_per_s": [r, p, y], "damping": z},
     "jitter": {"sigma_arcsec": s, "periods_s": [min, max]},
     "ephemeris": {"offset_sigma_m": b, "drift_sigma_mps": [along, cross, radial], "once_per_rev_m": a},
     "camera": {"angle_prior_px": p, "focal_prior_px": q},
     "dem": {"sigma_scale": k},
     "observations": {"tie_sigma_scale": t, "gcp_pixel_sigma_scale": g, "gcp_sigma_scale": p},
     "source": {"attitude": "pre-flight", ...},
     "fit": {"passes": [...], "levels": {"attitude.value_sigma_arcsec.roll": {"value", "sigma", ...}}}}

A section or a field left out takes its pre-flight default; an unknown one is refused, naming it.
``source`` says where each section's levels came from (``pre-flight``, ``input``, ``learned``)
and ``fit`` how ``misrgraph noise fit`` learned them; both are informative only.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

from misrgraph.errors import FileFormatError, InputError
from misrgraph.io.h5 import atomic_file
from misrgraph.model.noise import NOISE_MODEL_VERSION, NoiseModel

__all__ = ["read_noise_model", "save_noise_model", "NOISE_MODEL_KIND", "SECTIONS"]

NOISE_MODEL_KIND = "misrgraph noise model"
SECTIONS = ("attitude", "jitter", "ephemeris", "camera", "dem", "observations")


def save_noise_model(
    model: NoiseModel,
    path: str | os.PathLike[str],
    source: dict[str, str] | None = None,
    fit: dict[str, Any] | None = None,
) -> None:
    """Write ``model`` to ``path`` atomically; ``source`` names where each section's levels came
    from; ``fit``: how the learned levels were estimated (``misrgraph noise fit``: the passes and
    each level's estimate with its 1 sigma), kept in the file for the record."""
    data = {"kind": NOISE_MODEL_KIND, **model.to_dict()}
    data["source"] = {s: (source or {}).get(s, "pre-flight") for s in SECTIONS}
    if fit is not None:
        data["fit"] = fit
    with atomic_file(path) as fh:
        fh.write(json.dumps(data, indent=2) + "\n")


def read_noise_model(path: str | os.PathLike[str]) -> tuple[NoiseModel, dict[str, str]]:
    """The noise model in ``path`` and where each section's levels came from.

    Raises
    ------
    FileFormatError
        When the file is missing, not JSON, not a noise model, of another version, or holds a
        field that is unknown or out of range (the message names it).
    """
    p = Path(path)
    try:
        data: Any = json.loads(p.read_text())
    except FileNotFoundError:
        raise FileFormatError(p, "no such file") from None
    except OSError as exc:
        raise FileFormatError(p, f"cannot read ({exc.strerror})") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise FileFormatError(p, f"not JSON ({exc})") from None
    if not isinstance(data, dict) or data.get("kind") != NOISE_MODEL_KIND:
        raise FileFormatError(p, f"not a noise model (its 'kind' must be {NOISE_MODEL_KIND!r})")
    if data.get("version") != NOISE_MODEL_VERSION:
        raise FileFormatError(
            p, f"noise model version {data.get('version')!r}; this misrgraph reads {NOISE_MODEL_VERSION}"
        )
    source = {s: str((data.get("source") or {}).get(s, "input")) for s in SECTIONS}
    fields = {k: v for k, v in data.items() if k not in ("kind", "source", "fit")}
    try:
        return NoiseModel.from_dict(fields), source
    except InputError as exc:
        raise FileFormatError(p, str(exc)) from None
