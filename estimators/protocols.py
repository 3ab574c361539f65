"""The interface the estimators need from a model, stated once (instead of duck typing).

`HybridModel` (models.knode) satisfies it, and so does any small kinematic model an observer builds.
Arrays: x (n,) or a batch (B, n) of sigma points; u (p,) or (B, p); y (m,) or (B, m).
"""
from __future__ import annotations

from typing import Any, Protocol, runtime_checkable


@runtime_checkable
class StateSpaceModel(Protocol):
    """Discrete-time model x_{k+1} = step(x_k, u_k, dt), y_k = h(x_k, u_k)."""

    @property
    def n(self) -> int:
        """Number of states."""

    @property
    def n_inputs(self) -> int:
        """Number of inputs (0 for an autonomous model)."""

    @property
    def n_meas(self) -> int:
        """Number of measurements."""

    def step(self, x: Any, u: Any, dt: float) -> Any:
        """Next state(s); works on numpy arrays (batched) and on CasADi symbols."""

    def h(self, x: Any, u: Any = None) -> Any:
        """Predicted measurement(s)."""
