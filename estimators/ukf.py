"""UKF (eq. 3) on filterpy's UnscentedKalmanFilter and MerweScaledSigmaPoints.

Three changes to the textbook loop, all for models that are neural networks: every sigma point goes
through the model in one batched call (filterpy calls fx once per point); the covariance is kept
symmetric positive definite so that long runs never die in a Cholesky factorisation; and each covariance
is factorised once, with the factor kept for the next sigma points (filterpy factorises it twice more).

Where the time goes: with the model compiled (`compiled_sigma_functions`) but the loop in Python
(`BatchedUKF`), most of a step is numpy and ctypes overhead around the model (the update, with its inverse of
S, and the predict alike), not the model's arithmetic.  So with a compiler the whole loop runs in C (`ukf.c`
via `estimators.native.ukf_native`, the same algorithm; S is solved by Cholesky, not inverted), and a step's
time is nearly all the model's (the timings are on the results page `docs/results/speed.md`).  `BatchedUKF`
is the reference and the path for models without a compiler (numpy model).
"""
from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike

from learnest.models.checks import check_inputs, check_sequence

from .covariance_factor import repairs_warned, spd_factor
from .params import EstimatorParams
from .protocols import StateSpaceModel
from .results import FilterResult

if TYPE_CHECKING:
    from .native.ukf_native import NativeUKF
    from .ukf_filterpy import BatchedUKF

__all__ = ["SigmaFunctions", "compiled_sigma_functions", "make_ukf", "run_ukf", "spd_factor"]


def _rows(u: np.ndarray, count: int) -> np.ndarray:
    """u repeated for each sigma point (np.broadcast_to costs several times more on these sizes)."""
    out = np.empty((count, len(u)))
    out[:] = u
    return out


class SigmaFunctions(tuple):
    """The pair (fx, hx) of `compiled_sigma_functions`, plus ``native``: the whole filter loop in C over
    the same compiled functions (`estimators.native.ukf_native`), or None when ukf.c could not be built."""

    native: NativeUKF | None

    def __new__(cls, fx, hx, native: NativeUKF | None = None):
        pair = super().__new__(cls, (fx, hx))
        pair.native = native
        return pair


def compiled_sigma_functions(model: StateSpaceModel, dt: float,
                             cache_dir: str | Path | None = None) -> SigmaFunctions | None:
    """fx(sigmas, dt, u) and hx(sigmas, u) over the 2n+1 sigma points as compiled C (`estimators.native.codegen`),
    or None without a working compiler (CasADi's interpreter would be slower than numpy here).  With them
    comes the C filter loop `run_ukf` uses (`SigmaFunctions.native`).

    Why: the numpy model costs one interpreted call per array operation, dozens for a KNODE's or the
    quadrotor prior's RK4 step (unstack/stack per stage), and that overhead, not the arithmetic, sets a
    step's time; compiled, the same arithmetic runs in one call and gives the same numbers to rounding
    (the timings are on the results page `docs/results/speed.md`).  The model's numbers (weights,
    physical parameters) and dt are an input (`estimators.parametric`): one library per architecture.
    """
    import casadi as ca

    from .native.codegen import compiled, mapped, model_key
    from .native.ukf_native import NativeUKF, load_library
    from .parametric import symbolic_model

    n, count = model.n, 2 * model.n + 1
    x, u = ca.SX.sym("x", n), ca.SX.sym("u", model.n_inputs)
    symbolic = symbolic_model(model, dt)
    theta = symbolic.params
    f, h = symbolic.model.step(x, u, symbolic.dt), symbolic.model.h(x, u)
    step, meas = ca.Function("lrn_ukf_f", [x, u, theta], [f]), ca.Function("lrn_ukf_h", [x, u, theta], [h])
    # a second filter of this model in this process loads its library without generating code
    key = model_key(ca.Function("lrn_model", [x, u, theta], [f, h]), "ukf", count)
    # mapped over the sigma points, θ shared (not repeated)
    f_c, h_c = compiled([mapped(step, "lrn_ukf_fx", count, (2,)), mapped(meas, "lrn_ukf_hx", count, (2,))],
                        cache_dir=cache_dir, key=key)
    if f_c.backend != "c":
        return None
    f_c.inputs[2][0] = symbolic.values
    h_c.inputs[2][0] = symbolic.values

    def fx(sigmas, step_dt, u):
        f_c.inputs[0][...], f_c.inputs[1][...] = sigmas, u
        f_c.inputs[2][0, 0] = step_dt       # θ[0] is dt
        return f_c()[0].copy()

    def hx(sigmas, u):
        h_c.inputs[0][...], h_c.inputs[1][...] = sigmas, u
        return h_c()[0].copy()

    lib = load_library(cache_dir)
    native = None if lib is None else NativeUKF(lib, f_c, h_c, n, model.n_meas, model.n_inputs)
    return SigmaFunctions(fx, hx, native)


def make_ukf(params: EstimatorParams, alpha: float = 1e-3, beta: float = 2.0, kappa: float = 0.0,
             compiled: bool = False, codegen_dir: str | Path | None = None,
             sigma_functions: tuple | None = None) -> BatchedUKF:
    """A `BatchedUKF` for ``params.model`` with Merwe points (alpha, beta, kappa), x = x0 (n,), P = P0 (n, n).

    ``params``' Q (n, n) and R (m, m) are used as given (no validation here; `run_ukf` validates).
    ``predict`` and ``update`` take the input as the keyword ``u``, shape (p,).  ``compiled``: evaluate the
    model on the sigma points as compiled C (the model must accept CasADi symbols, as `HybridModel` does);
    the first filter of a model architecture compiles it (~1-5 s, cached in ``codegen_dir`` like the MHE's
    functions; default ``~/.cache/learnest/codegen``).  ``sigma_functions``: the (fx, hx) pair of
    `compiled_sigma_functions`, built once and reused for many filters of one model (then ``compiled`` is
    not consulted); filters sharing a pair must run one after the other (it writes into shared buffers).
    """
    from .ukf_filterpy import BatchedUKF, VectorizedMerwePoints  # filterpy on first use (module docstring)

    model, dt = params.model, params.dt
    n = model.n
    points = VectorizedMerwePoints(n, alpha=alpha, beta=beta, kappa=kappa)
    functions = sigma_functions
    if functions is None and compiled:
        functions = compiled_sigma_functions(model, dt, codegen_dir)
    if functions is None:
        functions = (lambda sigmas, dt, u: model.step(sigmas, _rows(u, len(sigmas)), dt),
                     lambda sigmas, u: model.h(sigmas, _rows(u, len(sigmas))))
    ukf = BatchedUKF(dim_x=n, dim_z=params.R.shape[0], dt=dt, points=points, fx=functions[0], hx=functions[1])
    ukf.x, ukf.Q, ukf.R = params.x0.copy(), params.Q, params.R
    ukf._set_covariance(params.P0)
    return ukf


def run_ukf(params: EstimatorParams, y: ArrayLike, u: ArrayLike | None = None, *, alpha: float = 1e-3,
            compiled: bool = False, codegen_dir: str | Path | None = None,
            sigma_functions: tuple | None = None) -> FilterResult:
    """Filter a whole sequence: update with y[0] at x0, then predict with u[k-1] and update with y[k].

    Parameters
    ----------
    params : EstimatorParams
        The model (`StateSpaceModel`: ``n``, ``n_inputs``, ``n_meas``, ``step``, ``h``), dt (s), Q (n, n) per
        step (may be singular), R (m, m), and the first state's guess x0 (n,) with its covariance P0 (n, n).
    y : array_like, shape (T, m)
        Measurements.
    u : array_like, shape (T, p), optional
        Inputs held over [t_k, t_k+1); None for a model without inputs.
    alpha : float
        Merwe sigma-point spread.
    compiled : bool
        Evaluate the model as compiled C (`make_ukf`); for a model used on many steps (an evaluation), not
        for one built per fit (every new model architecture compiles once).
    codegen_dir : path, optional
        Where the compiled functions are cached (`estimators.native.codegen`; default ``~/.cache/learnest/codegen``).
    sigma_functions : tuple, optional
        A prebuilt (fx, hx) pair of `compiled_sigma_functions` for this model and dt (`make_ukf`); when it
        carries the C loop (`SigmaFunctions.native`), the whole filter runs there (same algorithm).

    Returns
    -------
    FilterResult
        Means (T, n), covariances (T, n, n) and innovations (T, m); ``t = k * dt``.

    Raises
    ------
    InvalidInput
        On wrong shapes, non-finite values, a bad ``dt``, or a covariance that is not symmetric positive
        definite (Q may be semi-definite).

    Warns
    -----
    NumericalWarning
        Once per run, with the number of steps, when the filter's covariance lost positive definiteness and
        was repaired (`estimators.covariance_factor.spd_factor`).
    """
    model = params.model
    y = check_sequence("y", y, cols=model.n_meas)
    u = check_inputs(u, len(y), model.n_inputs)
    params = params.checked()
    if sigma_functions is None and compiled:
        sigma_functions = compiled_sigma_functions(model, params.dt, codegen_dir)
    with repairs_warned("UKF"):   # a repaired covariance warns once per run
        return _filter(params, sigma_functions, y, u, alpha)


def _filter(params: EstimatorParams, sigma_functions, y, u, alpha) -> FilterResult:
    """`run_ukf` on checked arguments: in C when the sigma functions carry the loop, else in Python."""
    n, dt = params.model.n, params.dt
    native = getattr(sigma_functions, "native", None)
    if native is not None:   # the same loop in C (module docstring)
        return native.run(y, u, dt, params.Q, params.R, params.x0, params.P0, alpha)
    ukf = make_ukf(params, alpha=alpha, sigma_functions=sigma_functions)
    ukf.sigmas_f = ukf._sigmas()
    means, innovations = np.empty((len(y), n)), np.empty(y.shape)
    covariances, log_likelihoods = np.empty((len(y), n, n)), np.empty(len(y))
    for k in range(len(y)):
        if k:
            ukf.predict(u=u[k - 1])
        ukf.update(y[k], u=u[k])
        means[k], innovations[k], covariances[k] = ukf.x, ukf.y, ukf.P
        log_likelihoods[k] = _log_density(ukf.y, ukf.S)
    return FilterResult(dt * np.arange(len(y)), means, covariances, innovations, log_likelihoods)


def _log_density(v: np.ndarray, S: np.ndarray) -> float:
    """log N(v; 0, S) for an innovation v (m,) and its covariance S (m, m); NaN when S is not positive definite."""
    try:
        factor = np.linalg.cholesky(S)
    except np.linalg.LinAlgError:
        return float("nan")
    white = np.linalg.solve(factor, v)
    return float(-0.5 * (len(v) * np.log(2 * np.pi) + 2 * np.sum(np.log(np.diag(factor))) + white @ white))
