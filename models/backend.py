"""One array namespace, three implementations: numpy (batched rows), torch (autograd), CasADi (symbols).

Priors and the MLP residual are written once against this small interface, so the model a UKF propagates,
the model IPOPT differentiates and the model Adam trains are the same function.
Convention: a state is the last axis in numpy/torch (shape (..., n)) and a column vector in CasADi (n, 1).
"""
from __future__ import annotations

import sys
from collections.abc import Callable
from types import ModuleType
from typing import TYPE_CHECKING, Any

import casadi as ca
import numpy as np

if TYPE_CHECKING:
    import torch


def _torch() -> ModuleType:
    # torch is imported on first use: reading flights, filtering with numpy and building CasADi problems
    # never pay its ~2 s import (the CLI's ingest, the service's pages, a notebook's le.ukf)
    import torch

    return torch


def _torch_function(name: str) -> staticmethod:
    """torch.<name>, looked up on first call (a staticmethod of `TorchOps`)."""
    return staticmethod(lambda x: getattr(_torch(), name)(x))


class NumpyOps:
    """numpy namespace: a state is the last axis, shape (..., n); leading axes are a batch (sigma points)."""

    name = "numpy"
    sin, cos, tan, arctan, tanh, sqrt = np.sin, np.cos, np.tan, np.arctan, np.tanh, np.sqrt

    @staticmethod
    def unstack(x: np.ndarray) -> list[np.ndarray]:
        """Components of the last axis: (..., n) -> n arrays of shape (...)."""
        return [x[..., i] for i in range(x.shape[-1])]

    @staticmethod
    def stack(items: list) -> np.ndarray:
        """Inverse of `unstack`: items of shape (...) (scalars broadcast) -> (..., len(items))."""
        try:
            return np.stack(items, axis=-1)  # the common case: every item has the batch shape
        except ValueError:
            return np.stack(np.broadcast_arrays(*items), axis=-1)

    @staticmethod
    def concat(items: list[np.ndarray]) -> np.ndarray:
        """Join along the last (state) axis."""
        return np.concatenate(items, axis=-1)

    @staticmethod
    def linear(z: np.ndarray, weight: np.ndarray, bias: np.ndarray) -> np.ndarray:
        """weight (out, in), bias (out,) numpy arrays: y = W z + b for each row of z."""
        return z @ weight.T + bias

    @staticmethod
    def zeros_like_first(x: np.ndarray) -> np.ndarray | float:
        """A zero of one state component's shape: zeros(x.shape[:-1]) for a batch, 0.0 for one state."""
        return np.zeros(x.shape[:-1]) if x.ndim > 1 else 0.0


class TorchOps:
    """torch namespace (autograd for training): a state is the last axis, shape (..., n)."""

    name = "torch"

    sin, cos, tan = _torch_function("sin"), _torch_function("cos"), _torch_function("tan")
    arctan, tanh, sqrt = _torch_function("atan"), _torch_function("tanh"), _torch_function("sqrt")

    @staticmethod
    def unstack(x: torch.Tensor) -> list[torch.Tensor]:
        """Components of the last axis: (..., n) -> n tensors of shape (...)."""
        return list(_torch().unbind(x, dim=-1))

    @staticmethod
    def stack(items: list[torch.Tensor]) -> torch.Tensor:
        """Inverse of `unstack`, broadcasting the items to one shape first."""
        torch = _torch()
        return torch.stack(torch.broadcast_tensors(*items), dim=-1)

    @staticmethod
    def concat(items: list[torch.Tensor]) -> torch.Tensor:
        """Join along the last (state) axis."""
        return _torch().cat(items, dim=-1)

    @staticmethod
    def linear(z: torch.Tensor, weight: Any, bias: Any) -> torch.Tensor:
        """y = z Wᵀ + b over the last axis; weight (out, in), bias (out,) tensors or float64 arrays."""
        torch = _torch()
        return torch.nn.functional.linear(z, torch.as_tensor(weight), torch.as_tensor(bias))

    @staticmethod
    def zeros_like_first(x: torch.Tensor) -> torch.Tensor:
        """Zeros of shape x.shape[:-1] and x's dtype."""
        return _torch().zeros(x.shape[:-1], dtype=x.dtype)


class CasadiOps:
    """CasADi namespace (symbols for IPOPT): a state is a column vector, shape (n, 1)."""

    name = "casadi"
    sin, cos, tan, arctan, tanh, sqrt = ca.sin, ca.cos, ca.tan, ca.atan, ca.tanh, ca.sqrt

    @staticmethod
    def unstack(x: Any) -> list:
        """Rows of a column vector (n, 1) -> n scalar expressions."""
        return [x[i] for i in range(x.shape[0])]

    @staticmethod
    def stack(items: list) -> Any:
        """Scalar expressions -> a column vector (vertcat)."""
        return ca.vertcat(*items)

    @staticmethod
    def concat(items: list) -> Any:
        """Join column vectors (vertcat)."""
        return ca.vertcat(*items)

    @staticmethod
    def linear(z: Any, weight: Any, bias: Any) -> Any:
        """y = W z + b for a column vector z; weight (out, in), bias (out,) numpy arrays as constants, or
        CasADi matrices (out, in), (out, 1) of symbols (`Residual.parametric`: the weights as an input)."""
        if isinstance(weight, (ca.SX, ca.MX)):
            return weight @ z + bias
        return ca.DM(np.asarray(weight)) @ z + ca.DM(np.asarray(bias))

    @staticmethod
    def zeros_like_first(x: Any) -> float:
        """0.0 (a CasADi state is never batched)."""
        return 0.0


#: A state or input in any namespace: numpy ndarray (..., n), torch Tensor (..., n) or CasADi SX/MX/DM (n, 1).
Array = Any

OPS = {"numpy": NumpyOps, "torch": TorchOps, "casadi": CasadiOps}


def ops_for(x: Any) -> type[NumpyOps] | type[TorchOps] | type[CasadiOps]:
    """Pick the namespace from the array type, so callers never pass it explicitly."""
    torch = sys.modules.get("torch")  # a tensor exists only once torch has been imported
    if torch is not None and isinstance(x, torch.Tensor):
        return TorchOps
    if isinstance(x, (ca.SX, ca.MX, ca.DM)):
        return CasadiOps
    return NumpyOps


def rk4_step(f: Callable[[Array, Array], Array], x: Array, u: Array, dt: float) -> Array:
    """One explicit RK4 step of x' = f(x, u) with u held over the step; works in every namespace.

    Parameters
    ----------
    f : callable
        Continuous vector field f(x, u) -> dx/dt, same shape as x.
    x : ndarray (..., n), Tensor (..., n) or CasADi (n, 1)
        State(s) at the start of the step.
    u : array or None
        Input, held constant (zero-order hold).
    dt : float
        Step, s.

    Returns
    -------
    Same type and shape as ``x``: the state after ``dt``.
    """
    k1 = f(x, u)
    k2 = f(x + 0.5 * dt * k1, u)
    k3 = f(x + 0.5 * dt * k2, u)
    k4 = f(x + dt * k3, u)
    return x + (dt / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
