"""``misrgraph bench knot-prior``: the knots' NEES and error under other knot priors, in closed form,
on the passes a ``bench worlds`` run fitted its noise models on.

For one attitude angle of one adjusted pass, the ``n`` knots ``x`` (value arcsec, rate arcsec/s;
``2n`` numbers, knot-major) have data information ``D`` (what the image observations tell about
them: the inverse of their adjusted covariance minus the prior they were adjusted with). Under a
zero-mean prior of precision ``L`` the estimate is ``x_hat = P (D y)`` with ``P = (D + L)^-1``
and ``y`` the data (``y = x + v``, ``v ~ N(0, D^-1)``), so its error ``x_hat - x = P (D v - L x)``
has covariance

    E = P (L C L + D) P,        C = Cov(x) (the truth's),

and the expected NEES per dimension is ``tr(E P^-1) / 2n = tr(L C L P + D P) / 2n`` (1 when
``L = C^-1``). The knots' truth is what the bench scores them against
(:func:`misrgraph.evaluate.score.true_knots`): the world's attitude error projected onto the
spline, ``C = C_band + C_jitter`` (:func:`misrgraph.model.errormodels.projected_band_covariance`
of the world's band process and of its jitter).

The passes are those the world's noise model was fitted on (``fit.passes`` of
``world<w>_<size>_noise.json`` in the workdir). The priors are compared, per angle, on each
pass's own knots (the pre-flight spacing in every world, also where the bench's oracle uses
denser knots):

- ``process``: the damped process at the world's levels (:func:`oracle_noise_model`), the
  oracle's knot prior;
- ``process + jitter``: its covariance plus the world's jitter projected onto the knots (a knot
  prior with a jitter component of its own);
- ``learned process``: the damped process of the noise model the bench fitted for the world
  (``world<w>_<size>_noise.json`` in the workdir);
- ``learned process + jitter``: plus that model's jitter (the pre-flight level, which the noise fit
  does not learn);
- ``exact``: ``C`` itself (NEES 1; its error is the least any prior reaches on these data).

Per world and prior: the NEES per dimension pooled over the passes and angles
(``sum tr(...) / sum 2n``, as the bench pools a pass's knots) and the RMS error of the knots'
values (arcsec).
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any, Callable

import numpy as np

from misrgraph.errors import FileFormatError, InputError

__all__ = ["expected_knot_error", "run_bench_knot_prior", "PRIORS"]

log = logging.getLogger(__name__)

#: the priors compared (module docstring), in the order the page shows them
PRIORS = ("process", "process + jitter", "learned process", "learned process + jitter", "exact")


def expected_knot_error(
    data_info: np.ndarray, prior_precision: np.ndarray, truth_cov: np.ndarray
) -> tuple[float, np.ndarray]:
    """The expected NEES summed over the block's dimensions, ``tr(L C L P + D P)``, and the error
    covariance ``P (L C L + D) P`` of the estimate under prior ``L`` (module docstring), from the
    data information ``D``, the prior precision ``L`` and the truth's covariance ``C`` (all
    ``(m, m)``, the same units)."""
    d, lp, c = (0.5 * (m + m.T) for m in (data_info, prior_precision, truth_cov))
    p = np.linalg.inv(d + lp)
    m = lp @ c @ lp + d
    return float(np.trace(m @ p)), p @ m @ p


def _fitted_passes(noise_file: Path, wd: Path) -> list[Path]:
    """The passes the noise model in ``noise_file`` was fitted on (its ``fit.passes``), found by
    their directory's name in ``wd`` (the workdir may have moved since)."""
    try:
        names = json.loads(noise_file.read_text())["fit"]["passes"]
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise FileFormatError(noise_file, f"not a fitted noise model ({exc!r})") from None
    files = [wd / Path(n).parent.name / Path(n).name for n in names]
    for f in files:
        if not f.exists():
            raise FileFormatError(f, "a pass the noise model was fitted on is missing")
    return files


def run_bench_knot_prior(
    workdir: str | Path,
    worlds: list[str] | None = None,
    size: str = "reduced",
    progress: Callable[[str], None] | None = None,
) -> dict[str, Any]:
    """The closed-form study of the module docstring on the noise models a ``bench worlds`` run kept
    in ``workdir`` and the passes each was fitted on; ``worlds``: names of
    :data:`~misrgraph.bench.worlds.WORLDS` (default: every world the workdir holds a noise model of).

    Returns ``{"size", "worlds": {name: {"passes", "blocks", "priors": {prior: {"nees",
    "value_rms_arcsec"}}}}}``."""
    from misrgraph.bench.worlds import WORLD_SIZES, WORLDS, oracle_noise_model, world_files
    from misrgraph.estimate.noisefit import _attitude_blocks, knot_prior_precision
    from misrgraph.io.noise import read_noise_model
    from misrgraph.model.errormodels import projected_band_covariance
    from misrgraph.model.noise import NoiseModel
    from misrgraph.runs.noise import read_pass_levels
    from misrgraph.sim.simulate import ScenarioConfig

    wd = Path(workdir)
    if not wd.is_dir():
        raise InputError("workdir", str(wd), "the --workdir of a 'misrgraph bench worlds' run")
    if size not in WORLD_SIZES:
        raise InputError("size", size, tuple(WORLD_SIZES))
    names = list(WORLDS) if worlds is None else list(worlds)
    for n in names:
        if n not in WORLDS:
            raise InputError("worlds", n, tuple(WORLDS))
    out: dict[str, Any] = {}
    for name in names:
        *_, noise_file = world_files(wd, name, size)
        if not noise_file.exists():
            if worlds is not None:
                raise InputError("worlds", name, f"a world whose fitted noise model is in {wd}")
            continue
        files = _fitted_passes(noise_file, wd)
        if progress:
            progress(f"{name}: {len(files)} fitted passes")
        cfg = ScenarioConfig.from_dict(dict(WORLDS[name]))
        if cfg.attitude_spectral_slope != 0 or cfg.attitude_lines or cfg.jitter_lines:
            raise InputError("worlds", name, "a world whose attitude error is a flat band plus jitter")
        oracle = oracle_noise_model(cfg)
        learned, _ = read_noise_model(noise_file)
        passes = [read_pass_levels(f) for f in files]
        sums = {p: [0.0, 0.0, 0.0, 0] for p in PRIORS}  # NEES sum, value squared error sum, values, dims
        blocks = 0
        for a in range(3):
            for t, d_info, *_ in _attitude_blocks(passes, NoiseModel(), a):
                c = projected_band_covariance(t, cfg.attitude_sigma_arcsec[a], tuple(cfg.attitude_periods_s))
                jit = projected_band_covariance(t, cfg.jitter_arcsec, tuple(cfg.jitter_periods_s))
                c = c + jit
                priors = {}
                for label, model in (("", oracle), ("learned ", learned)):
                    at = model.attitude
                    sig = float(at.value_sigma_arcsec[a])
                    lam = float(at.rate_sigmas()[a]) / sig
                    lp = knot_prior_precision(t, sig, lam, float(at.damping))
                    j = projected_band_covariance(t, float(model.jitter.sigma_arcsec), tuple(model.jitter.periods_s))
                    priors[label + "process"] = lp
                    priors[label + "process + jitter"] = knot_prior_precision(
                        t, sig, lam, float(at.damping), "process+jitter", j
                    )
                priors["exact"] = np.linalg.inv(c)
                for prior, lp in priors.items():
                    nees, err = expected_knot_error(d_info, lp, c)
                    s = sums[prior]
                    s[0] += nees
                    s[1] += float(np.trace(err[0::2, 0::2]))
                    s[2] += t.size
                    s[3] += 2 * t.size
                blocks += 1
        out[name] = {
            "passes": len(files),
            "blocks": blocks,
            "priors": {
                p: {"nees": s[0] / s[3], "value_rms_arcsec": float(np.sqrt(s[1] / s[2]))} for p, s in sums.items()
            },
        }
        log.info("%s: %d fitted passes, %d knot blocks", name, len(files), blocks)
    if not out:
        raise InputError("workdir", str(wd), "the --workdir of a 'misrgraph bench worlds' run (no fitted passes in it)")
    return {"size": size, "worlds": out}
