"""Moving horizon estimation, eq. (2): Gauss–Newton on the banded normal equations (default) or IPOPT.

`solver="gauss-newton"` (default, `estimators.mhe_gn`) solves each window to convergence with an exact
gradient and a banded Cholesky, compiled CasADi functions doing the model's arithmetic; it equals the
IPOPT solution within 1e-6 (tests/estimators/test_mhe.py) at a fraction of the time (`docs/results/speed.md`).
`solver="ipopt"` is the reference described below, kept unchanged.

IPOPT: the NLP for horizon N is built once (dynamics as one CasADi Function mapped over the window, so a KNODE
becomes plain symbols) and re-solved every step with new parameters (measurements, inputs, arrival
state x̄ and weight P_k⁻¹).  Each solve is warm-started, primal and dual, from the previous solution
shifted by one sample.  During the first N steps the horizon grows (full-information estimation); those
shorter problems are built once each and cached.

Decision variables per window: states x_{k-N..k} and process noises w_{k-N..k-1}; the equality
constraints x_{i+1} = f(x_i, u_i) + w_i carry the duals that the warm start reuses; measurement noises
v_i = y_i - h(x_i) are substituted into the cost.
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import casadi as ca
import numpy as np
from numpy.typing import ArrayLike

from learnest.models.checks import check_sequence, check_vector
from learnest.models.presets import MHE_SOLVERS, check_mhe_options

from .covariance import linearized_covariances
from .mhe_gn import GaussNewtonWindowSolver
from .params import EstimatorParams
from .results import MHEResult

# The values an IPOPT / nlpsol option takes (the Hessian callback is a CasADi Function).
SolverOption = bool | int | float | str | ca.Function

IPOPT_OPTIONS: dict[str, SolverOption] = {
    "ipopt.print_level": 0, "print_time": False, "ipopt.sb": "yes",
    "ipopt.tol": 1e-8, "ipopt.max_iter": 200,
    "ipopt.warm_start_init_point": "yes", "ipopt.mu_init": 1e-6,
    "ipopt.warm_start_bound_push": 1e-9, "ipopt.warm_start_mult_bound_push": 1e-9,
}


SOLVERS = MHE_SOLVERS


@dataclass
class _Window:
    solver: ca.Function
    length: int  # number of state nodes (N + 1 in steady state)


class MHE:
    """One estimator object per (model, dt, weights, horizon); `run` estimates a whole sequence.

    Parameters
    ----------
    params : EstimatorParams
        The model (discrete dynamics `step(x, u, dt)` and measurement `h(x, u)`, n states, p inputs, m
        outputs, CasADi-traceable), dt (s), the process noise Q (n, n, definite: it is inverted), the
        measurement noise R (m, m), the initial arrival covariance P0 (n, n) and the first arrival state x0
        (n,), which `run` may replace per record.
    horizon : int
        N: a window holds N + 1 states (fewer while the record is shorter: growing horizon).
    arrival : {"ekf", "fixed"}
        "fixed" keeps P_k = P0 for the arrival cost; "ekf" propagates P_k with an EKF recursion along the
        arrival states (the usual approximation of the arrival cost's curvature).
    arrival_update : {"filtering", "smoothing"}
        Where the arrival mean comes from as the window slides (`models.presets.MHE_ARRIVAL_UPDATES`):
        "filtering" (default), the prediction f(x̂_{s|s}) that the EKF-propagated covariance describes;
        "smoothing", the paper's eq. (2), the last window's estimate of the new first step.
    solver : {"gauss-newton", "ipopt"}
        "gauss-newton" (default) is the fast solver of `estimators.mhe_gn`; "ipopt" the reference.
    warm_start, hessian, ipopt_options
        IPOPT only: warm start from the shifted solution, the Hessian it is given ("cost" or "exact"),
        extra IPOPT options.
    tol, max_iter, codegen_dir, compiler
        Gauss–Newton only: step tolerance in state units, iterations per window (None: to
        convergence; 1: a real-time iteration), where compiled functions are cached, which C compiler
        ("auto" or None for CasADi's interpreter).
    """

    def __init__(self, params: EstimatorParams, horizon: int = 20, arrival: str = "ekf", warm_start: bool = True,
                 hessian: str = "cost", ipopt_options: dict[str, SolverOption] | None = None,
                 solver: str = "gauss-newton", tol: float = 1e-9, max_iter: int | None = None,
                 codegen_dir: str | Path | None = None, compiler: str | None = "auto",
                 arrival_update: str = "filtering") -> None:
        check_mhe_options(horizon, solver, arrival, hessian, max_iter, arrival_update)   # InvalidInput, naming them
        self.params = params.checked(singular_q=False)
        self.hessian, self.solver = hessian, solver
        model = self.params.model
        self.model, self.dt, self.horizon = model, self.params.dt, int(horizon)
        self.n, self.p, self.m = model.n, model.n_inputs, model.n_meas
        self.Q, self.R, self.P0 = self.params.Q, self.params.R, self.params.P0
        self.arrival, self.arrival_update, self.warm_start = arrival, arrival_update, warm_start
        self.options = {**IPOPT_OPTIONS, **(ipopt_options or {})}
        if not warm_start:
            self.options["ipopt.warm_start_init_point"] = "no"
            self.options.pop("ipopt.mu_init")
        x, u = ca.SX.sym("x", self.n), ca.SX.sym("u", self.p)
        self.step_fn = ca.Function("f", [x, u], [model.step(x, u, self.dt)])
        self.h_fn = ca.Function("h", [x, u], [model.h(x, u)])
        if arrival == "ekf":
            self.jac_f = ca.Function("F", [x, u], [ca.jacobian(model.step(x, u, self.dt), x)])
            self.jac_h = ca.Function("H", [x, u], [ca.jacobian(model.h(x, u), x)])
        self._windows: dict[int, _Window] = {}
        self.stats = {"solves": 0, "iterations": 0, "failures": 0}
        self._gn: GaussNewtonWindowSolver | None = None
        if solver == "gauss-newton":
            self._gn = GaussNewtonWindowSolver(self, tol=tol, max_iter=max_iter, cache_dir=codegen_dir,
                                               compiler=compiler)
            self.stats = self._gn.stats

    def prepare(self) -> MHE:
        """Build everything a run needs (IPOPT: every growing-horizon window), so timing excludes it."""
        if self.solver == "ipopt":
            for length in range(1, self.horizon + 2):
                self.window(length)
        return self

    # -- NLP construction ---------------------------------------------------------------------------
    def window(self, length: int) -> _Window:
        """The NLP over `length` state nodes, built on first use and kept."""
        if length not in self._windows:
            self._windows[length] = self._build(length)
        return self._windows[length]

    def _build(self, length: int) -> _Window:
        n, p, m = self.n, self.p, self.m
        X = ca.SX.sym("X", n, length)
        W = ca.SX.sym("W", n, length - 1)
        Y = ca.SX.sym("Y", m, length)
        U = ca.SX.sym("U", p, length)
        x_bar = ca.SX.sym("x_bar", n)
        P_inv = ca.SX.sym("P_inv", n, n)
        Q_inv, R_inv = ca.DM(np.linalg.inv(self.Q)), ca.DM(np.linalg.inv(self.R))
        e0 = X[:, 0] - x_bar
        cost = ca.bilin(P_inv, e0, e0)                                       # arrival cost
        V = Y - self.h_fn.map(length)(X, U)                                  # v_i = y_i - h(x_i)
        cost += ca.sum2(ca.sum1(V * (R_inv @ V)))
        constraints = []
        if length > 1:
            cost += ca.sum2(ca.sum1(W * (Q_inv @ W)))
            predicted = self.step_fn.map(length - 1)(X[:, :-1], U[:, :-1])
            constraints = [ca.vec(X[:, 1:] - predicted - W)]
        z = ca.vertcat(ca.vec(X), ca.vec(W))
        params = ca.vertcat(ca.vec(Y), ca.vec(U), x_bar, ca.vec(P_inv))
        g = ca.vertcat(*constraints) if constraints else ca.SX(0, 1)
        options = dict(self.options)
        if self.hessian == "cost":
            options["hess_lag"] = self._cost_hessian(z, params, cost, g.shape[0])
        problem = {"x": z, "p": params, "f": cost, "g": g}
        return _Window(ca.nlpsol(f"mhe_{length}", "ipopt", problem, options), length)

    @staticmethod
    def _cost_hessian(z: ca.SX, p: ca.SX, cost: ca.SX, n_constraints: int) -> ca.Function:
        """The Lagrangian's Hessian without the dynamics' curvature (λᵀ∇²g): the cost's exact Hessian only.
        For a KNODE it avoids second derivatives of the network through RK4, which dominate the exact
        Hessian's cost.  It is positive semi-definite when h is linear (the quadrotor, the cartpole); with
        the robot's range sensors it need not be, and IPOPT's inertia correction handles that.  The optimum
        is the same; only IPOPT's path to it changes."""
        lam_f, lam_g = ca.SX.sym("lam_f"), ca.SX.sym("lam_g", n_constraints)
        hess = ca.triu(lam_f * ca.hessian(cost, z)[0])
        return ca.Function("hess_lag", [z, p, lam_f, lam_g], [hess],
                           ["x", "p", "lam_f", "lam_g"], ["triu_hess_gamma_x_x"])

    # -- estimation ---------------------------------------------------------------------------------
    def run(self, y: ArrayLike, u: ArrayLike, x0: ArrayLike | None = None,
            progress: Callable[[int], object] | None = None, *, covariances: bool = False) -> MHEResult:
        """Estimate x̂_{k|k} for every k of a record.

        Parameters
        ----------
        y : array_like, shape (T, m)
            Measurements.
        u : array_like, shape (T, p)
            Inputs held over [t_k, t_k+1) (width 0 for a model without inputs).
        x0 : array_like, shape (n,), optional
            The prior guess of this record's first state (arrival x̄ at k=0); default the bundle's.  An MHE
            is built once per model and tuning (building costs seconds) and run on records of other first states.
        progress : callable, optional
            Called with each k as its window is solved.
        covariances : bool
            Also linearise an EKF along the estimates for their covariances (`estimators.covariance`); off by
            default: it costs several times the Gauss–Newton run, and an evaluation uses the means only.

        Returns
        -------
        MHEResult
            ``t = k * dt`` (s), means (T, n), covariances (T, n, n) or None, and the windows whose solver failed.
        """
        y = check_sequence("y", y, cols=self.m)
        T = len(y)
        u = check_sequence("u", np.asarray(u, dtype=float).reshape(T, -1), rows=T, cols=self.p)
        x_bar = self.params.x0 if x0 is None else check_vector("x0", x0, self.n)
        failures = int(self.stats.get("failures", 0))
        means = self._gn.run(y, u, x_bar, progress) if self._gn is not None else self._run_ipopt(y, u, x_bar, progress)
        return MHEResult(self.dt * np.arange(T), means,
                         linearized_covariances(self.params, means, u) if covariances else None,
                         int(self.stats.get("failures", 0)) - failures)

    def _run_ipopt(self, y: np.ndarray, u: np.ndarray, x_bar: np.ndarray,
                   progress: Callable[[int], object] | None) -> np.ndarray:
        """`run`'s means with IPOPT solving every window."""
        T = len(y)
        P_arrival = self.P0.copy()
        estimates = np.empty((T, self.n))
        guess_X = np.tile(x_bar[:, None], (1, 1))
        guess_W, guess_lam = np.zeros((self.n, 0)), np.zeros(0)
        for k in range(T):
            start = max(0, k - self.horizon)
            length = k - start + 1
            win = self.window(length)
            params = np.concatenate([y[start:k + 1].T.ravel("F"), u[start:k + 1].T.ravel("F"),
                                     x_bar, np.linalg.inv(P_arrival).ravel("F")])
            x_init = np.concatenate([guess_X.ravel("F"), guess_W.ravel("F")])
            args: dict[str, np.ndarray | float] = {"x0": x_init, "p": params, "lbg": 0.0, "ubg": 0.0}
            if self.warm_start and guess_lam.size == self.n * (length - 1):
                args["lam_g0"] = guess_lam
            sol = win.solver(**args)
            self._record(win.solver)
            z = np.asarray(sol["x"]).ravel()
            X = z[: self.n * length].reshape(length, self.n).T
            W = z[self.n * length:].reshape(length - 1, self.n).T
            lam = np.asarray(sol["lam_g"]).ravel()
            estimates[k] = X[:, -1]
            guess_X, guess_W, guess_lam, x_bar, P_arrival = self._shift(X, W, lam, u, k, start, x_bar,
                                                                        P_arrival, y, estimates)
            if progress:
                progress(k)
        return estimates

    def solve_window_ipopt(self, X: np.ndarray, u_win: np.ndarray, y_win: np.ndarray, x_bar: np.ndarray,
                           P_inv: np.ndarray) -> tuple[np.ndarray, bool]:
        """(X*, success): one window (X (L, n) as the initial guess) solved by IPOPT; the Gauss–Newton
        solver's fallback."""
        L = len(X)
        win = self.window(L)
        W = X[1:] - np.asarray(self.step_fn.map(L - 1)(X[:-1].T, u_win[:-1].T)).T if L > 1 else np.zeros((0, self.n))
        params = np.concatenate([y_win.ravel(), u_win.ravel(), x_bar, P_inv.ravel("F")])
        sol = win.solver(x0=np.concatenate([X.ravel(), W.ravel()]), p=params, lbg=0.0, ubg=0.0)
        z = np.asarray(sol["x"]).ravel()
        return z[: self.n * L].reshape(L, self.n), bool(win.solver.stats().get("success", True))

    def _shift(self, X: np.ndarray, W: np.ndarray, lam: np.ndarray, u: np.ndarray, k: int, start: int,
               x_bar: np.ndarray, P_arrival: np.ndarray, y: np.ndarray,
               estimates: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Next window's warm start and arrival cost: the filtering update x̄_{s+1} <- f(x̂_{s|s}), s = k-N.

        P is propagated by the EKF recursion from s to s+1: updated with y_s, then predicted, P_{s+1|s}.  The
        mean it describes is the prediction from the estimate the MHE gave when s ended its window, x̂_{s|s}.
        The smoothed X*[:, 1] of this window already holds the measurements s+1..k, which the next window
        counts again: with the mocap hidden, the accelerometer's hold on the velocity (through the rotor drag)
        would count up to N times, and the estimate would drift.  For a linear model the MHE then equals the
        Kalman filter.  The paper's smoothing update (``arrival_update="smoothing"``) takes X*[:, 1] itself."""
        x_next = np.asarray(self.step_fn(X[:, -1], u[k])).ravel()
        slides = k + 1 - self.horizon > start  # the window start moves forward at the next step
        if not slides:
            return (np.column_stack([X, x_next]), np.column_stack([W, np.zeros(self.n)]),
                    np.concatenate([lam, np.zeros(self.n)]), x_bar, P_arrival)
        if self.arrival == "ekf":
            P_arrival = self._ekf_arrival(X[:, 0], u[start], y[start], P_arrival)
        lam_next = np.concatenate([lam[self.n:], np.zeros(self.n)]) if lam.size else lam
        return (np.column_stack([X[:, 1:], x_next]), np.column_stack([W[:, 1:], np.zeros(self.n)]),
                lam_next, self.arrival_mean(X[:, 1], estimates[start], u[start]), P_arrival)

    def arrival_mean(self, smoothed: np.ndarray, filtered: np.ndarray, u: np.ndarray) -> np.ndarray:
        """The next window's arrival mean (n,): ``smoothed`` (this window's estimate of the next first step) for
        the smoothing update, else the prediction from ``filtered``, the estimate at this window's first step."""
        if self.arrival_update == "smoothing":
            return np.array(smoothed, dtype=float)
        return np.asarray(self.step_fn(filtered, u)).ravel()

    def _ekf_arrival(self, x: np.ndarray, u: np.ndarray, y: np.ndarray, P: np.ndarray) -> np.ndarray:
        H = np.asarray(self.jac_h(x, u))
        S = H @ P @ H.T + self.R
        P = P - P @ H.T @ np.linalg.solve(S, H @ P)
        F = np.asarray(self.jac_f(x, u))
        P = F @ P @ F.T + self.Q
        return 0.5 * (P + P.T)

    def _record(self, solver: ca.Function) -> None:
        stats = solver.stats()
        self.stats["solves"] += 1
        self.stats["iterations"] += int(stats.get("iter_count", 0))
        self.stats["failures"] += int(not stats.get("success", True))
