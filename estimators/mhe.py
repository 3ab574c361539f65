"""Moving horizon estimation, eq. (2), in CasADi + IPOPT.

The NLP for horizon N is built once (dynamics as one CasADi Function mapped over the window, so a KNODE
becomes plain symbols) and re-solved every step with new parameters (measurements, inputs, arrival
state x̄ and weight P_k⁻¹).  Each solve is warm-started, primal and dual, from the previous solution
shifted by one sample.  During the first N steps the horizon grows (full-information estimation); those
shorter problems are built once each and cached.

Decision variables per window: states x_{k-N..k} and process noises w_{k-N..k-1}; the equality
constraints x_{i+1} = f(x_i, u_i) + w_i carry the duals that the warm start reuses; measurement noises
v_i = y_i - h(x_i) are substituted into the cost.
"""
from __future__ import annotations

from dataclasses import dataclass

import casadi as ca
import numpy as np

from learnest.models.checks import check_covariance, check_dt, check_sequence, check_vector

IPOPT_OPTIONS = {
    "ipopt.print_level": 0, "print_time": False, "ipopt.sb": "yes",
    "ipopt.tol": 1e-8, "ipopt.max_iter": 200,
    "ipopt.warm_start_init_point": "yes", "ipopt.mu_init": 1e-6,
    "ipopt.warm_start_bound_push": 1e-9, "ipopt.warm_start_mult_bound_push": 1e-9,
}


@dataclass
class _Window:
    solver: ca.Function
    length: int  # number of state nodes (N + 1 in steady state)


class MHE:
    """One estimator object per (model, dt, weights, horizon); `run` estimates a whole sequence.

    arrival: "fixed" keeps P_k = P0 for the arrival cost; "ekf" propagates P_k with an EKF recursion along
    the arrival states (the usual approximation of the arrival cost's curvature).
    """

    def __init__(self, model, dt, Q, R, P0, horizon: int = 20, arrival: str = "ekf",
                 warm_start: bool = True, hessian: str = "cost", ipopt_options: dict | None = None):
        if int(horizon) != horizon or horizon < 1:
            raise ValueError(f"horizon must be a positive integer, got {horizon}")
        if arrival not in ("fixed", "ekf"):
            raise ValueError(f"arrival must be 'fixed' or 'ekf', got {arrival!r}")
        if hessian not in ("cost", "exact"):
            raise ValueError(f"hessian must be 'cost' or 'exact', got {hessian!r}")
        self.hessian = hessian
        self.model, self.dt, self.horizon = model, check_dt(dt), int(horizon)
        self.n, self.p, self.m = model.n, model.n_inputs, model.n_meas
        self.Q = check_covariance("Q", Q, self.n)
        self.R = check_covariance("R", R, self.m)
        self.P0 = check_covariance("P0", P0, self.n)
        self.arrival, self.warm_start = arrival, warm_start
        self.options = {**IPOPT_OPTIONS, **(ipopt_options or {})}
        if not warm_start:
            self.options["ipopt.warm_start_init_point"] = "no"
            self.options.pop("ipopt.mu_init")
        x, u, w = ca.SX.sym("x", self.n), ca.SX.sym("u", self.p), ca.SX.sym("w", self.n)
        self.step_fn = ca.Function("f", [x, u], [model.step(x, u, self.dt)])
        self.h_fn = ca.Function("h", [x, u], [model.h(x, u)])
        if arrival == "ekf":
            self.jac_f = ca.Function("F", [x, u], [ca.jacobian(model.step(x, u, self.dt), x)])
            self.jac_h = ca.Function("H", [x, u], [ca.jacobian(model.h(x, u), x)])
        self._windows: dict[int, _Window] = {}
        self.stats = {"solves": 0, "iterations": 0, "failures": 0}

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
        p = ca.vertcat(ca.vec(Y), ca.vec(U), x_bar, ca.vec(P_inv))
        g = ca.vertcat(*constraints) if constraints else ca.SX(0, 1)
        options = dict(self.options)
        if self.hessian == "cost":
            options["hess_lag"] = self._cost_hessian(z, p, cost, g.shape[0])
        return _Window(ca.nlpsol(f"mhe_{length}", "ipopt", {"x": z, "p": p, "f": cost, "g": g}, options), length)

    @staticmethod
    def _cost_hessian(z, p, cost, n_constraints):
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
    def run(self, y, u, x0, progress=None) -> np.ndarray:
        """Estimate x̂_{k|k} for every k; x0 is the prior guess of the first state (arrival x̄ at k=0)."""
        y = check_sequence("y", y, cols=self.m)
        T = len(y)
        u = check_sequence("u", np.asarray(u, dtype=float).reshape(T, -1), rows=T, cols=self.p)
        x_bar = check_vector("x0", x0, self.n)
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
            args = dict(x0=x_init, p=params, lbg=0.0, ubg=0.0)
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
                                                                        P_arrival, y)
            if progress:
                progress(k)
        return estimates

    def _shift(self, X, W, lam, u, k, start, x_bar, P_arrival, y):
        """Next window's warm start and arrival cost (x̄_{k-N|k} <- x̂*_{k-N|k-1})."""
        x_next = np.asarray(self.step_fn(X[:, -1], u[k])).ravel()
        slides = k + 1 - self.horizon > start  # the window start moves forward at the next step
        if not slides:
            return (np.column_stack([X, x_next]), np.column_stack([W, np.zeros(self.n)]),
                    np.concatenate([lam, np.zeros(self.n)]), x_bar, P_arrival)
        if self.arrival == "ekf":
            P_arrival = self._ekf_arrival(X[:, 0], u[start], y[start], P_arrival)
        lam_next = np.concatenate([lam[self.n:], np.zeros(self.n)]) if lam.size else lam
        return (np.column_stack([X[:, 1:], x_next]), np.column_stack([W[:, 1:], np.zeros(self.n)]),
                lam_next, X[:, 1].copy(), P_arrival)

    def _ekf_arrival(self, x, u, y, P):
        H = np.asarray(self.jac_h(x, u))
        S = H @ P @ H.T + self.R
        P = P - P @ H.T @ np.linalg.solve(S, H @ P)
        F = np.asarray(self.jac_f(x, u))
        P = F @ P @ F.T + self.Q
        return 0.5 * (P + P.T)

    def _record(self, solver):
        stats = solver.stats()
        self.stats["solves"] += 1
        self.stats["iterations"] += int(stats.get("iter_count", 0))
        self.stats["failures"] += int(not stats.get("success", True))
