"""Mocap gaps as an input: a model whose position measurement one extra input switches off per step, and the
measurements that go with it (`estimators.yardsticks` explains why the gaps are run this way)."""
from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from .protocols import StateSpaceModel

POSITION_ROWS = (0, 1, 2)   # the mocap position in y = [p, a_meas] and in x = [p, v, a]


def gap_mask(n_samples: int, windows: Sequence[tuple[int, int]]) -> np.ndarray:
    """(T,) bool, True inside a gap."""
    inside = np.zeros(n_samples, dtype=bool)
    for first, stop in windows:
        inside[first:stop] = True
    return inside


class PositionGapModel:
    """A model whose position measurement can be switched off per step by one extra input (`estimators.yardsticks`).

    Inputs are the wrapped model's inputs followed by the mask (1: mocap present, 0: hidden); h's rows
    ``rows`` are multiplied by the mask, so a hidden step's position residual and its Jacobian are exactly
    zero when the measurement there is 0 (`masked_measurements`).  Works on numpy (batched sigma points),
    and on CasADi symbols (`parametric`), so the compiled UKF and MHE take it as any model.

    Parameters
    ----------
    model : StateSpaceModel
        The model (a `HybridModel`); ``kind``, ``system``, ``residual`` and ``meta`` are passed through,
        ``kind`` suffixed so the batch's caches tell the two apart.
    rows : sequence of int
        The measurement rows the mask switches (the mocap position: 0, 1, 2).
    """

    def __init__(self, model: StateSpaceModel, rows: Sequence[int] = POSITION_ROWS) -> None:
        self.model, self.rows = model, tuple(int(r) for r in rows)
        self.kind = f"{getattr(model, 'kind', 'model')}+mocap-gaps"
        self.system = getattr(model, "system", None)
        self.residual = getattr(model, "residual", None)
        self.meta = getattr(model, "meta", {})

    @property
    def n(self) -> int:
        """Number of states."""
        return self.model.n

    @property
    def n_inputs(self) -> int:
        """The wrapped model's inputs plus the mask."""
        return self.model.n_inputs + 1

    @property
    def n_meas(self) -> int:
        """Number of measurements (the wrapped model's)."""
        return self.model.n_meas

    def _split(self, u):
        p = self.model.n_inputs
        import casadi as ca
        if isinstance(u, (ca.SX, ca.MX, ca.DM)):
            return (u[:p] if p else ca.SX(0, 1)), u[p]
        u = np.asarray(u, dtype=float)
        return u[..., :p], u[..., p]

    def step(self, x, u, dt):
        """The wrapped model's step on its own inputs (the mask does not touch the dynamics)."""
        return self.model.step(x, self._split(u)[0], dt)

    def h(self, x, u=None):
        """The wrapped model's measurement with rows ``rows`` multiplied by the mask."""
        inner, mask = self._split(u)
        y = self.model.h(x, inner)
        import casadi as ca
        if isinstance(y, (ca.SX, ca.MX, ca.DM)):
            return ca.vertcat(*[y[i] * mask if i in self.rows else y[i] for i in range(y.shape[0])])
        y = np.array(y, dtype=float, copy=True)
        y[..., list(self.rows)] *= np.asarray(mask)[..., None]
        return y

    def parametric(self):
        """(model, θ, values) as `HybridModel.parametric`, the wrapped model's numbers as symbols."""
        inner, theta, values = self.model.parametric()
        return PositionGapModel(inner, self.rows), theta, values

    def __repr__(self) -> str:
        return f"PositionGapModel({self.model!r})"


def masked_measurements(y: np.ndarray, u: np.ndarray, inside: np.ndarray,
                        rows: Sequence[int] = POSITION_ROWS) -> tuple[np.ndarray, np.ndarray]:
    """(y, u) for `PositionGapModel`: the rows ``rows`` of y set to 0 inside the gaps, u with the mask
    (1 outside, 0 inside) appended; y (T, m), u (T, p), inside (T,) bool -> (T, m), (T, p + 1)."""
    y = np.array(y, dtype=float, copy=True)
    y[np.ix_(np.asarray(inside, dtype=bool), np.asarray(rows, dtype=int))] = 0.0
    u = np.asarray(u, dtype=float).reshape(len(y), -1)
    return y, np.column_stack([u, (~inside).astype(float)])
