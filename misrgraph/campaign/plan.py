"""The campaign's plan: which paths, which repeat passes, what sizes, and the digests that name
every output.

The seed's operational plan (section 2): calibrate the cameras on about a month of GCP passes,
then adjust about 30 % of six months of data -- at least four passes per path -- and build the
products of each path. A path is revisited every 16 days, so ``months`` of data hold
``ceil(months * 30.4375 / 16)`` repeat passes of each path (cycle k starts 16 k days after the
epoch); the campaign adjusts ``min(K, max(passes_per_path, ceil(fraction * K)))`` of them, spread
evenly over the period.

Every output is named by a digest of its inputs and configuration (:func:`digest`): a SHA-256 over
the inputs' own content digests (each misrgraph file carries one), the configuration as canonical
JSON and the software version. A rerun finds what is done by name.
"""

from __future__ import annotations

import hashlib
import json
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from misrgraph import __version__
from misrgraph.config import Config
from misrgraph.errors import InputError
from misrgraph.io.imagery import OBSERVATION_SETS
from misrgraph.misr.som import N_BLOCKS
from misrgraph.model.noise import NoiseModel
from misrgraph.model.orbit import REPEAT_PATHS

__all__ = [
    "CampaignConfig",
    "CampaignPlan",
    "PathPlan",
    "SIZES",
    "plan_campaign",
    "choose",
    "simulated_pass_id",
    "digest",
    "parse_paths",
    "DAYS_PER_MONTH",
    "REPEAT_DAYS",
]

#: mean month (days) and Terra's repeat cycle (days)
DAYS_PER_MONTH = 30.4375
REPEAT_DAYS = 16

#: Scenario sizes: the GCP month and the path passes (ScenarioConfig fields), the SOM blocks of
#: each path's Projection Parameters. ``standard`` is what users run; ``reduced`` is the test
#: suite's and the benchmarks' size.
SIZES: dict[str, dict[str, Any]] = {
    "standard": {
        "month": {},
        "path": {"n_tie_points": 600, "n_check_points": 20, "duration_s": 2700.0},
        "pp_blocks": 10,
    },
    "reduced": {
        "month": {"n_gcps": 24, "month_days": 16},
        "path": {"n_tie_points": 80, "n_check_points": 20, "duration_s": 600.0, "start_lat_deg": 50.0},
        "pp_blocks": 2,
    },
}


@dataclass(frozen=True)
class CampaignConfig(Config):
    """What the campaign does (units in the names; unknown keys are rejected by ``from_dict``).

    ``paths``: WRS-like path numbers 1..233 (empty: all 233, the seed's plan); ``months`` of data
    after ``epoch_date``; ``fraction`` of each path's repeat passes adjusted, at least
    ``passes_per_path``; ``size`` of the simulated scenarios (:data:`SIZES`); ``truth`` of the
    simulator (``independent``: a world the estimator does not share; ``model``: algebra checks);
    ``pp_blocks``: SOM blocks of each path's Projection Parameters (0: the size's default);
    ``products``: build the per-path incremental state and products; ``roi``: build each path's
    Reference Orbit Imagery from its state too (the path's inputs need whole-swath strips and a
    SOM DEM: when the campaign simulates them, it renders ``roi_blocks`` blocks from the one under
    the middle of the pass, all nine cameras, at ~80 s a block and pass on 2 cores);
    ``observations``: what the calibration, the adjustments and the path states use --
    ``"simulated"`` (each pass's own) or ``"matched"`` (measured in the imagery by ``misrgraph
    match``: the campaign then simulates the month and the paths with imagery, GCP chips and tie
    windows, and matches them as part of their inputs; brought inputs must have been matched).
    """

    months: float = 6.0
    fraction: float = 0.3
    paths: tuple = ()
    passes_per_path: int = 4
    size: str = "standard"
    truth: str = "independent"
    seed: int = 0
    epoch_date: str = "2001-06-15"
    pp_blocks: int = 0
    products: bool = True
    roi: bool = False
    roi_blocks: int = 1
    observations: str = "simulated"
    #: the levels the calibration and the adjustments assume (:class:`~misrgraph.model.noise.NoiseModel`,
    #: ``campaign --noise-model``); None: the pre-flight levels
    noise: NoiseModel | None = None
    #: the campaign over years (:mod:`misrgraph.campaign.years`): a calibration window every
    #: ``recalibrate_months`` months (0: one calibration for the whole campaign), the calibrations
    #: watched with false-alarm probability ``monitor_alpha``, each repeat pass adjusted with the
    #: camera-model version valid for its orbit
    recalibrate_months: float = 0.0
    monitor_alpha: float = 0.05
    #: learn the noise levels on the campaign's own first passes (``misrgraph noise fit``): the
    #: first ``noise_fit_passes`` planned passes (one path after another, each path's earliest
    #: first) are adjusted with ``noise`` (or the pre-flight levels), the model fitted on them,
    #: and every other pass and path adjusted with it; 0: no fit
    noise_fit_passes: int = 0
    #: the simulated true camera's changes over the years, as ``simulate --config`` takes them
    #: (:class:`~misrgraph.sim.simulate.ScenarioConfig`: drifts, annual terms, steps; zero at
    #: ``epoch_date``; steps dated after it)
    camera_drifts: tuple = ()
    camera_annual: tuple = ()
    camera_steps: tuple = ()

    def __post_init__(self) -> None:
        if not self.months > 0:
            raise InputError("months", self.months, "a number of months > 0")
        if not 0 < self.fraction <= 1:
            raise InputError("fraction", self.fraction, "a fraction in (0, 1]")
        if self.passes_per_path < 1:
            raise InputError("passes_per_path", self.passes_per_path, "an integer >= 1")
        bad = [p for p in self.paths if isinstance(p, bool) or not isinstance(p, int) or not 1 <= p <= REPEAT_PATHS]
        if bad or len(set(self.paths)) != len(self.paths):
            raise InputError("paths", list(self.paths), f"distinct path numbers in 1..{REPEAT_PATHS}")
        if self.size not in SIZES:
            raise InputError("size", self.size, tuple(SIZES))
        if self.truth not in ("independent", "model"):
            raise InputError("truth", self.truth, ("independent", "model"))
        if not 0 <= self.pp_blocks <= N_BLOCKS:
            raise InputError("pp_blocks", self.pp_blocks, f"0 (the size's default) to {N_BLOCKS}")
        if self.roi and not self.products:
            raise InputError("roi", self.roi, "False unless products is True (the ROI is built from each path's state)")
        if isinstance(self.roi_blocks, bool) or not isinstance(self.roi_blocks, int) or not 1 <= self.roi_blocks <= 20:
            raise InputError("roi_blocks", self.roi_blocks, "an integer number of blocks in 1..20")
        if self.observations not in OBSERVATION_SETS:
            raise InputError("observations", self.observations, OBSERVATION_SETS)
        if not (isinstance(self.recalibrate_months, (int, float)) and self.recalibrate_months >= 0):
            raise InputError(
                "recalibrate_months (--recalibrate)",
                self.recalibrate_months,
                "a number of months >= 0 (0: one calibration)",
            )
        if self.recalibrate_months and self.months / self.recalibrate_months < 4 - 1e-9:
            raise InputError(
                "recalibrate_months (--recalibrate)",
                self.recalibrate_months,
                f"at most months / 4 = {self.months / 4:g} (the monitor needs at least 4 calibrations)",
            )
        if (
            isinstance(self.noise_fit_passes, bool)
            or not isinstance(self.noise_fit_passes, int)
            or self.noise_fit_passes < 0
        ):
            raise InputError(
                "noise_fit_passes (--noise-fit-passes)", self.noise_fit_passes, "a whole number >= 0 (0: no fit)"
            )
        if not 0 < self.monitor_alpha < 1:
            raise InputError(
                "monitor_alpha (--monitor-alpha)", self.monitor_alpha, "a false-alarm probability in (0, 1)"
            )
        if self.camera_change:
            from misrgraph.sim.simulate import ScenarioConfig

            ScenarioConfig.from_dict({**self.camera_change, "epoch_date": self.epoch_date})
            early = [s for s in self.camera_steps if str(s[0]) <= self.epoch_date]
            if early:
                raise InputError("camera_steps", list(early[0]), f"a date after epoch_date {self.epoch_date}")

    @property
    def camera_change(self) -> dict[str, Any]:
        """The true camera's changes as simulate's fields (empty when there are none)."""
        terms = {
            "camera_drifts": self.camera_drifts,
            "camera_annual": self.camera_annual,
            "camera_steps": self.camera_steps,
        }
        return {k: [list(x) for x in v] for k, v in terms.items() if v}

    @property
    def blocks(self) -> int:
        """SOM blocks of each path's Projection Parameters."""
        return self.pp_blocks or int(SIZES[self.size]["pp_blocks"])


@dataclass(frozen=True)
class PathPlan:
    """One path: the repeat passes available in the period, the chosen ones (``cycles``: indices
    0..available-1) and their pass ids."""

    path: int
    available: int
    cycles: tuple[int, ...]
    pass_ids: tuple[str, ...]


@dataclass(frozen=True)
class CampaignPlan:
    config: CampaignConfig
    paths: list[PathPlan] = field(default_factory=list)

    @property
    def n_passes(self) -> int:
        return sum(len(p.cycles) for p in self.paths)

    def fit_pass_ids(self) -> list[str]:
        """The passes the noise levels are learned on (``config.noise_fit_passes`` of them): each
        path's earliest pass in turn, then each path's second, and so on."""
        longest = max((len(p.pass_ids) for p in self.paths), default=0)
        order = [p.pass_ids[i] for i in range(longest) for p in self.paths if i < len(p.pass_ids)]
        return order[: self.config.noise_fit_passes]

    def to_dict(self) -> dict[str, Any]:
        return {
            # fields at their defaults that came after the first campaigns are left out, so that a
            # campaign without them plans as one did before they existed
            "config": {k: v for k, v in self.config.to_dict().items() if not (k in _LATER and v == _LATER[k])},
            "paths": {
                str(p.path): {"available": p.available, "cycles": list(p.cycles), "pass_ids": list(p.pass_ids)}
                for p in self.paths
            },
            "passes_planned": self.n_passes,
        }


_LATER: dict[str, Any] = {
    "noise": None,
    "recalibrate_months": 0.0,
    "monitor_alpha": 0.05,
    "noise_fit_passes": 0,
    "camera_drifts": (),
    "camera_annual": (),
    "camera_steps": (),
}


def parse_paths(text: str) -> tuple[int, ...]:
    """``"37,38"`` or ``"30-33,40"`` -> path numbers (an InputError names a bad item)."""
    out: list[int] = []
    for item in (t.strip() for t in text.split(",")):
        if not item:
            continue
        try:
            if "-" in item:
                a, b = (int(x) for x in item.split("-", 1))
                out.extend(range(a, b + 1))
            else:
                out.append(int(item))
        except ValueError:
            raise InputError("--paths", item, "path numbers separated by commas, or ranges A-B") from None
    if not out:
        raise InputError("--paths", text, "at least one path number")
    return tuple(out)


def choose(available: int, cfg: CampaignConfig) -> tuple[int, ...]:
    """Indices of the passes adjusted out of ``available``: ``min(available, max(passes_per_path,
    ceil(fraction * available)))`` of them, spread evenly (first and last included)."""
    n = min(available, max(cfg.passes_per_path, math.ceil(cfg.fraction * available - 1e-9)))
    return tuple(int(k) for k in np.unique(np.round(np.linspace(0, available - 1, n)).astype(int)))


def simulated_pass_id(path: int, cycle: int) -> str:
    """The simulator's id of repeat cycle ``cycle`` of ``path`` (its orbit is 233 cycle)."""
    return f"P{path:03d}_O{REPEAT_PATHS * cycle:04d}"


def plan_campaign(cfg: CampaignConfig) -> CampaignPlan:
    """The passes a simulated campaign adjusts: per path, the chosen repeat cycles (see the module docstring)."""
    available = max(1, math.ceil(cfg.months * DAYS_PER_MONTH / REPEAT_DAYS - 1e-9))
    cycles = choose(available, cfg)
    paths = cfg.paths or tuple(range(1, REPEAT_PATHS + 1))
    return CampaignPlan(
        cfg, [PathPlan(int(p), available, cycles, tuple(simulated_pass_id(int(p), k) for k in cycles)) for p in paths]
    )


def digest(*parts: Any) -> str:
    """SHA-256 (hex) of JSON-serialisable parts and the software version, canonically encoded."""
    h = hashlib.sha256()
    h.update(json.dumps([__version__, *parts], sort_keys=True, default=str).encode())
    return h.hexdigest()
