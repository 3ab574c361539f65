"""A model's noise: what its filters assume of the process and the sensors (Q, R, P0), stored with the model.

A filter's estimate depends on its noise as much as on its dynamics: on the NanoBench flights a prior-only UKF whose
velocity and acceleration noise were raised beats every learned residual run with the fixed noise (the results page
`docs/results/noise.md`).  So a model carries its own `NoiseModel`, identified on its training flights
(`estimators.noise_identification`), and a comparison of two models runs each with its own noise, tuned the same way
on the same flights.  The fixed settings of the system classes (the paper's, Sec. V) stay one named choice:
`NoiseModel.paper`.

Noise is diagonal and set per *block* of states or measurements that share a physical meaning and unit
(`blocks`): on the flight systems the position, velocity and acceleration states, and the mocap position
and accelerometer measurements.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING

import numpy as np

from learnest.errors import InvalidInput

if TYPE_CHECKING:
    from .systems import System

# What produced a noise model: the system class's fixed settings, or maximum likelihood on flights.
PAPER, IDENTIFIED = "paper", "identified"
NOISE_SOURCES = (PAPER, IDENTIFIED)

# Physical bounds on a standard deviation per step (process) or per sample (measurement), in the state's or
# measurement's own SI unit: below, a filter would trust the block absolutely; above, not at all.  An
# identification that ends at a bound says so (`NoiseModel.detail`).
STD_BOUNDS = (1e-9, 1e3)


def blocks(names: tuple[str, ...]) -> dict[str, list[int]]:
    """Indices of ``names`` grouped by physical quantity: ``px, py, pz`` -> ``{"p": [0, 1, 2]}``.

    A name ending in an axis letter (x, y, z) after at least one other character joins the block of its
    stem; any other name is a block of its own.
    """
    out: dict[str, list[int]] = {}
    for i, name in enumerate(names):
        stem = name[:-1] if len(name) > 1 and name[-1] in "xyz" else name
        out.setdefault(stem, []).append(i)
    return out


@dataclass(frozen=True)
class NoiseModel:
    """Diagonal noise of one model's filters.

    Attributes
    ----------
    process_std : tuple of float, (n,)
        Standard deviation of the process noise per step, in each state's unit (Q = diag(process_std²)).
    meas_std : tuple of float, (m,)
        Standard deviation of each measurement's noise, in its unit (R = diag(meas_std²)).
    initial_std : tuple of float, (n,)
        Standard deviation of the first state estimate (P0 = diag(initial_std²)).
    source : {"paper", "identified"}
        The system class's fixed settings, or identified on flights.
    detail : dict
        How it was identified (empty for ``"paper"``): the flights, the mean log-likelihood per
        step before and after (nats), the scale of each block relative to the paper's noise, the blocks that
        stayed fixed, evaluations and seconds (`estimators.noise_identification.identify_noise`).
    """

    process_std: tuple
    meas_std: tuple
    initial_std: tuple
    source: str = PAPER
    detail: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.source not in NOISE_SOURCES:
            raise InvalidInput(f"noise source must be one of {', '.join(NOISE_SOURCES)}, not {self.source!r}")
        for name in ("process_std", "meas_std", "initial_std"):
            values = tuple(float(v) for v in getattr(self, name))
            if not all(math.isfinite(v) and v >= 0 for v in values):
                raise InvalidInput(f"noise {name} must be finite and non-negative, got {values}")
            object.__setattr__(self, name, values)

    @classmethod
    def paper(cls, system: System) -> NoiseModel:
        """The fixed settings of ``system``'s class (the paper's, Sec. V)."""
        return cls(system.process_noise_std, system.meas_noise_std, system.initial_std, PAPER)

    @property
    def Q(self) -> np.ndarray:
        """Process noise covariance per step, (n, n)."""
        return np.diag(np.square(self.process_std))

    @property
    def R(self) -> np.ndarray:
        """Measurement noise covariance, (m, m)."""
        return np.diag(np.square(self.meas_std))

    @property
    def P0(self) -> np.ndarray:
        """Initial estimate covariance, (n, n)."""
        return np.diag(np.square(self.initial_std))

    def apply(self, system: System) -> System:
        """``system`` with this noise as its estimators' settings (its Q, R, P0).

        Raises
        ------
        InvalidInput
            If the sizes do not match the system's states and measurements.
        """
        if (len(self.process_std), len(self.meas_std), len(self.initial_std)) != (system.n, system.n_meas, system.n):
            raise InvalidInput(f"a noise model of {len(self.process_std)} states and {len(self.meas_std)} "
                               f"measurements does not fit the {system.name} system ({system.n}, {system.n_meas})")
        return replace(system, process_noise_std=self.process_std, meas_noise_std=self.meas_std,
                       initial_std=self.initial_std)

    def describe(self, system: System) -> dict:
        """Per block, the standard deviations in words a reader can check: ``{"process": {"v": "3.2e-03 m/s per
        step", ...}, "measurement": {...}, "source": ...}`` (units from the block's stem: p m, v m/s, a m/s²)."""
        units = {"p": "m", "v": "m/s", "a": "m/s²"}

        def table(stds, names):
            return {stem: f"{stds[idx[0]]:.3g} {units.get(stem, '')}".rstrip()
                    for stem, idx in blocks(tuple(names)).items()}

        return {"source": self.source, "process_per_step": table(self.process_std, system.state_names),
                "measurement": table(self.meas_std, system.meas_names),
                "initial": table(self.initial_std, system.state_names)}

    def with_model_spread(self, variance: np.ndarray) -> NoiseModel:
        """This noise with ``variance`` (n,) added to the process noise per step: what an ensemble's spread along a
        flight stands for (`models.ensemble.spread_variance`); ``detail["ensemble_spread_std"]`` keeps it."""
        variance = np.asarray(variance, dtype=float)
        if variance.shape != (len(self.process_std),) or not np.all(np.isfinite(variance)) or np.any(variance < 0):
            raise InvalidInput(f"an ensemble's spread must be {len(self.process_std)} finite non-negative variances")
        std = np.sqrt(np.square(self.process_std) + variance)
        return replace(self, process_std=tuple(std), detail={**self.detail,
                                                             "ensemble_spread_std": np.sqrt(variance).tolist()})

    def to_dict(self) -> dict:
        """JSON form (lists of floats)."""
        return {"process_std": list(self.process_std), "meas_std": list(self.meas_std),
                "initial_std": list(self.initial_std), "source": self.source, "detail": dict(self.detail)}

    @classmethod
    def from_dict(cls, data: dict) -> NoiseModel:
        """Inverse of `to_dict`.

        Raises
        ------
        InvalidInput
            If a field is missing or not a list of non-negative numbers.
        """
        try:
            return cls(tuple(data["process_std"]), tuple(data["meas_std"]), tuple(data["initial_std"]),
                       str(data.get("source", PAPER)), dict(data.get("detail") or {}))
        except (KeyError, TypeError, ValueError) as err:
            raise InvalidInput(f"not a stored noise model ({err})") from None
