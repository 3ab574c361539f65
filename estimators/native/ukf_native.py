"""The UKF's whole filter loop as one C call (`ukf.c`), over the compiled sigma-point functions.

`ukf_filterpy.BatchedUKF` is the same algorithm in numpy and stays the reference (and the path for a
model without a compiler).  Why C: with the model's sigma-point functions compiled, the numpy and ctypes
overhead of a Python loop around them would take most of a step; `ukf.c` calls the compiled functions
through pointers, as `gn.c` does for the MHE.  A covariance that Cholesky cannot factor is handed back to
Python for `spd_factor` (its eigenvalue lift and eigen square root), and the loop resumes: the same repair as
the Python filter's.
"""
from __future__ import annotations

import ctypes
from pathlib import Path

import numpy as np

from learnest.errors import InvalidInput

from ..covariance_factor import spd_factor
from ..results import FilterResult

C_FLAGS = ("-O2", "-fPIC", "-shared")   # a small hand-written file: -O2 compiles in well under a second


class _Fn(ctypes.Structure):
    """ukf.c's lrn_fn: a compiled CasADi function and its argument and work arrays."""

    _fields_ = [("fn", ctypes.c_void_p), ("arg", ctypes.c_void_p), ("res", ctypes.c_void_p),
                ("iw", ctypes.c_void_p), ("w", ctypes.c_void_p), ("mem", ctypes.c_longlong)]


class _Problem(ctypes.Structure):
    """ukf.c's lrn_ukf."""

    _fields_ = [*[(name, ctypes.c_int) for name in ("n", "m", "p", "count", "T")], ("scale", ctypes.c_double),
                ("Wm", ctypes.c_void_p), ("Wc", ctypes.c_void_p), ("fx", _Fn), ("hx", _Fn),
                *[(name, ctypes.c_void_p) for name in ("Q", "R", "y", "u", "means", "covs", "innov", "loglik", "x", "P",
                                                       "L", "work")],
                ("k", ctypes.c_int), ("stage", ctypes.c_int)]


def merwe_weights(n: int, alpha: float, beta: float = 2.0, kappa: float = 0.0) -> tuple[np.ndarray, np.ndarray, float]:
    """(Wm, Wc, scale): filterpy's MerweScaledSigmaPoints weights (2n+1 each) and sqrt(λ + n)."""
    lam = alpha**2 * (n + kappa) - n
    Wm = np.full(2 * n + 1, 0.5 / (n + lam))
    Wc = Wm.copy()
    Wm[0] = lam / (n + lam)
    Wc[0] = lam / (n + lam) + (1.0 - alpha**2 + beta)
    return Wm, Wc, float(np.sqrt(alpha**2 * (n + kappa)))


def load_library(cache_dir=None, compiler="auto"):
    """lu.c + ukf.c compiled and loaded (cached by its hash like the model's code), or None without a compiler."""
    from .codegen import load_source

    source = "\n".join(Path(__file__).with_name(name).read_text() for name in ("lu.c", "ukf.c"))
    return load_source(source, cache_dir, compiler, flags=C_FLAGS)


class NativeUKF:
    """`run_ukf`'s loop in C over compiled, mapped fx (``lrn_ukf_fx``) and hx (``lrn_ukf_hx``).

    Parameters
    ----------
    lib : ctypes.CDLL
        `load_library`'s result.
    f_c, h_c : codegen.CompiledFunction
        The mapped sigma-point functions (inputs sigmas, u, θ with θ[0] = dt), θ already filled.
    n, m, p : int
        State, measurement and input sizes.

    Filters sharing one instance must run one after the other (they share its buffers).
    """

    def __init__(self, lib, f_c, h_c, n: int, m: int, p: int):
        self.f_c, self.h_c, self.n, self.m, self.p = f_c, h_c, n, m, p
        self._run = lib.lrn_ukf_run
        self._run.argtypes, self._run.restype = [ctypes.c_void_p], ctypes.c_int
        size = lib.lrn_ukf_work_size
        size.argtypes, size.restype = [ctypes.c_int] * 3, ctypes.c_int
        self.work = np.zeros(size(n, m, 2 * n + 1))
        self.fx, self.hx = _Fn(*f_c.pointers()), _Fn(*h_c.pointers())
        self._lib = lib   # keep the library loaded as long as this object lives

    def run(self, y: np.ndarray, u: np.ndarray, dt: float, Q: np.ndarray, R: np.ndarray, x0: np.ndarray,
            P0: np.ndarray, alpha: float, beta: float = 2.0, kappa: float = 0.0) -> FilterResult:
        """The filter over y (T, m) with inputs u (T, p), checked by the caller (`run_ukf`) against its model.

        Raises
        ------
        InvalidInput
            If the sizes are not the ones these functions were compiled for (C would read and write past
            the arrays: a ``sigma_functions`` built for another model).
        """
        n, m, T = self.n, self.m, len(y)
        expected = {"y": (T, m), "u": (T, self.p), "Q": (n, n), "R": (m, m), "x0": (n,), "P0": (n, n)}
        wrong = [f"{name} {np.shape(a)} (expected {expected[name]})" for name, a in
                 (("y", y), ("u", np.reshape(u, (T, -1)) if np.size(u) else np.zeros((T, 0))), ("Q", Q), ("R", R),
                  ("x0", x0), ("P0", P0)) if np.shape(a) != expected[name]]
        if wrong:
            raise InvalidInput(f"the compiled UKF functions were built for a model with n={n}, m={m}, p={self.p}: "
                               f"got {', '.join(wrong)}")
        Wm, Wc, scale = merwe_weights(n, alpha, beta, kappa)
        y, u = _c(y), _c(u.reshape(T, self.p))
        Q, R = _c(Q), _c(R)
        P, L = spd_factor(np.asarray(P0, dtype=float))
        x, P, L = _c(x0).copy(), _c(P).copy(), _c(L).copy()
        means, covariances, innovations = np.empty((T, n)), np.empty((T, n, n)), np.empty((T, m))
        log_likelihoods = np.empty(T)
        self.f_c.inputs[2][0, 0] = dt   # θ[0] is dt
        problem = _Problem(n=n, m=m, p=self.p, count=2 * n + 1, T=T, scale=scale, Wm=_address(Wm),
                           Wc=_address(Wc), fx=self.fx, hx=self.hx,
                           **{name: _address(a) for name, a in (("Q", Q), ("R", R), ("y", y), ("u", u),
                                                                ("means", means), ("covs", covariances),
                                                                ("innov", innovations), ("loglik", log_likelihoods),
                                                                ("x", x), ("P", P), ("L", L), ("work", self.work))},
                           k=0, stage=1)   # step 0: update only, from the factor of P0
        while (status := self._run(ctypes.addressof(problem))) == 1:
            # Cholesky failed on the new P: repair it exactly as the Python filter does, then resume
            repaired, factor = spd_factor(P)
            P[...], L[...] = repaired, factor
        if status == -1:
            raise RuntimeError("compiled CasADi function returned an error")
        if status == -2:
            raise np.linalg.LinAlgError(f"UKF innovation covariance singular at step {problem.k}")
        return FilterResult(dt * np.arange(T), means, covariances, innovations, log_likelihoods)


def _c(array) -> np.ndarray:
    return np.ascontiguousarray(array, dtype=np.float64)


def _address(array: np.ndarray) -> int:
    if not (array.flags.c_contiguous and array.dtype == np.float64):
        raise ValueError("expected a C-contiguous float64 array")
    return array.__array_interface__["data"][0]
