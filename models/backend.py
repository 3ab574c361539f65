"""One array namespace, three implementations: numpy (batched rows), torch (autograd), CasADi (symbols).

Priors and the MLP residual are written once against this small interface, so the model a UKF propagates,
the model IPOPT differentiates and the model Adam trains are the same function.
Convention: a state is the last axis in numpy/torch (shape (..., n)) and a column vector in CasADi (n, 1).
"""
from __future__ import annotations

import casadi as ca
import numpy as np
import torch


class NumpyOps:
    name = "numpy"
    sin, cos, tan, arctan, tanh, sqrt = np.sin, np.cos, np.tan, np.arctan, np.tanh, np.sqrt

    @staticmethod
    def unstack(x):
        return [x[..., i] for i in range(x.shape[-1])]

    @staticmethod
    def stack(items):
        try:
            return np.stack(items, axis=-1)  # the common case: every item has the batch shape
        except ValueError:
            return np.stack(np.broadcast_arrays(*items), axis=-1)

    @staticmethod
    def concat(items):
        return np.concatenate(items, axis=-1)

    @staticmethod
    def linear(z, weight, bias):
        """weight (out, in), bias (out,) numpy arrays: y = W z + b for each row of z."""
        return z @ weight.T + bias

    @staticmethod
    def zeros_like_first(x):
        return np.zeros(x.shape[:-1]) if x.ndim > 1 else 0.0


class TorchOps:
    name = "torch"
    sin, cos, tan, arctan, tanh, sqrt = torch.sin, torch.cos, torch.tan, torch.atan, torch.tanh, torch.sqrt

    @staticmethod
    def unstack(x):
        return list(torch.unbind(x, dim=-1))

    @staticmethod
    def stack(items):
        return torch.stack(torch.broadcast_tensors(*items), dim=-1)

    @staticmethod
    def concat(items):
        return torch.cat(items, dim=-1)

    @staticmethod
    def linear(z, weight, bias):
        return torch.nn.functional.linear(z, weight, bias)

    @staticmethod
    def zeros_like_first(x):
        return torch.zeros(x.shape[:-1], dtype=x.dtype)


class CasadiOps:
    name = "casadi"
    sin, cos, tan, arctan, tanh, sqrt = ca.sin, ca.cos, ca.tan, ca.atan, ca.tanh, ca.sqrt

    @staticmethod
    def unstack(x):
        return [x[i] for i in range(x.shape[0])]

    @staticmethod
    def stack(items):
        return ca.vertcat(*items)

    @staticmethod
    def concat(items):
        return ca.vertcat(*items)

    @staticmethod
    def linear(z, weight, bias):
        return ca.DM(np.asarray(weight)) @ z + ca.DM(np.asarray(bias))

    @staticmethod
    def zeros_like_first(x):
        return 0.0


OPS = {"numpy": NumpyOps, "torch": TorchOps, "casadi": CasadiOps}


def ops_for(x):
    """Pick the namespace from the array type, so callers never pass it explicitly."""
    if isinstance(x, torch.Tensor):
        return TorchOps
    if isinstance(x, (ca.SX, ca.MX, ca.DM)):
        return CasadiOps
    return NumpyOps


def rk4_step(f, x, u, dt):
    """One explicit RK4 step of x' = f(x, u) with u held; works in every namespace."""
    k1 = f(x, u)
    k2 = f(x + 0.5 * dt * k1, u)
    k3 = f(x + 0.5 * dt * k2, u)
    k4 = f(x + dt * k3, u)
    return x + (dt / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
