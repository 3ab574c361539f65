"""The MHE window solved by Gauss–Newton on its banded normal equations (the default MHE solver).

Problem.  With the process noises eliminated (w_i = x_{i+1} - f(x_i, u_i)), eq. (2) over a window of L
nodes is an unconstrained nonlinear least-squares problem in the states alone,

    min_X  ‖x_0 - x̄‖²_{P⁻¹} + Σ_{i<L} ‖y_i - h(x_i)‖²_{R⁻¹} + Σ_{i<L-1} ‖x_{i+1} - f(x_i)‖²_{Q⁻¹},

whose stationary points are exactly the KKT points IPOPT finds for the constrained form (the constraint
only names w_i).  Its Gauss–Newton matrix is block tridiagonal (L blocks of n×n, bandwidth 2n-1) and
positive definite (the arrival and Q terms alone make it so), so one step costs a block Cholesky of
~80k flops for L = 21, n = 9, not a sparse KKT solve.

Where the time goes, and why this design (the timings against IPOPT are on the results page
`docs/results/speed.md`):
- Calling a CasADi `Function` from Python converts every argument and result (numpy -> DM -> numpy), which
  costs more than a small model's arithmetic, so the model's arithmetic is CasADi-generated C, compiled once
  and called through ctypes
  (`estimators.native.codegen`, cached by content hash; CasADi's interpreter when there is no compiler).  The
  model's numbers (weights, physical parameters, dt) and Q⁻¹, R⁻¹ are inputs of that code, not constants
  in it, so it is compiled once per architecture, not once per trained model (`estimators.parametric`).
  CasADi's structure-exploiting NLP solvers (sqpmethod + qrqp/hpipm, fatrop) would solve the same problem, but each call
  pays the same conversions plus a generic QP setup; a problem this regular needs neither.
- Even through ctypes, driving the iterations from Python costs as much as their arithmetic (numpy and
  ctypes overhead on every call), so a window's whole loop runs in C (`gn.c`, `_NativeWindow`), calling the
  compiled CasADi functions through pointers; so does the EKF arrival update (a few thousand flops, which
  numpy's per-call overhead would dominate), and so does the recursion around the windows (the shift, the
  two nodes' Jacobians).  `_solve` and `_run` below are the same loops in Python, used with the interpreter.
- The exact Jacobian of one RK4 step of the network costs several times the step itself, its
  vector-Jacobian product a small multiple of it.  So every iterate gets the exact gradient (reverse mode
  over the window, one compiled call: "sweep"), and full Jacobians are taken only when they pay: once per window
  after the first step, and again whenever the contraction is slow.  Between, each node keeps the
  Jacobian of its last linearisation (shifted with the window).  The fixed point is the exact
  stationary point whatever Jacobians the matrix uses; they only set the rate.  Right after a
  re-linearisation the gradient comes from those Jacobians (F'λ, H'λ) instead of a sweep.
- Not done, and why: re-linearising only the nodes that moved.  After the first step every node moves
  by a similar amount (the acceleration states shift along the whole window), so re-linearising only the
  last nodes costs more iterations than it saves in Jacobians.  Nor -O2 for the model's functions: they
  run no faster than with -O1 and take several times longer to compile (`estimators.native.codegen`).
- The Gauss–Newton matrix is factored by a block Cholesky (Riccati-type) recursion in C (`btd.c`),
  O(L n³); LAPACK's banded dpbtrf on the same matrix is slower for 9×9 blocks (its blocking and threading
  overhead outweighs the arithmetic), and it remains the fallback without a compiler.
- A model linear in x (the quadrotor prior) has a quadratic cost: one step with exact Jacobians is the
  solution, and it stops there.
- Gauss–Newton drops the dynamics' curvature weighted by the multipliers Q⁻¹w; with a very curved
  network and the quadrotor's stiff Q (position noise 1e-5 m) full steps can cycle.  A window that does
  not converge in 30 iterations is handed to IPOPT (its line search), counted in `stats`.
Stopping: the step's ∞-norm below `tol`, or, once two successive steps are below 1e-4, the remaining
error the observed contraction predicts (ρ·s/(1-ρ), ρ = s_k/s_{k-1}) below `tol`.  The arrival-cost
recursion and the growing/sliding window are those of the IPOPT version, the EKF's Jacobians taken at
the solution's first node.
"""
from __future__ import annotations

import ctypes
import warnings

import casadi as ca
import numpy as np

from learnest.errors import NumericalWarning

from .native.block_tridiagonal import BlockTridiagonal, _address
from .native.codegen import compiled, mapped, model_key
from .parametric import symbolic_model

# The contraction estimate ρ = s_k/s_{k-1} predicts the remaining error only once both steps are small
# (asymptotic regime); from a large first step it can promise too much and stop short of IPOPT's solution.
RATE_REGIME = 1e-4


class GaussNewtonWindowSolver:
    """Runs the MHE recursion of `mhe` (an `estimators.mhe.MHE`) with Gauss–Newton windows.

    Parameters
    ----------
    mhe : MHE
        Supplies model, dt, Q, R, P0, horizon, arrival.
    tol : float
        Stop when the step (or the predicted remaining error) is below this, in state units (∞-norm).
    max_iter : int or None
        Iterations per window; None runs to convergence (at most 30 Gauss–Newton iterations, then IPOPT
        solves that window), 1 is a real-time iteration.
    cache_dir, compiler
        Passed to `estimators.native.codegen.compiled`.
    """

    def __init__(self, mhe, tol: float = 1e-9, max_iter: int | None = None, cache_dir=None, compiler="auto"):
        self.mhe = mhe
        self.tol, self.max_iter = float(tol), max_iter
        n, p, m = mhe.n, mhe.p, mhe.m
        self.Lmax = mhe.horizon + 1
        self.Qi, self.Ri = np.linalg.inv(mhe.Q), np.linalg.inv(mhe.R)
        self.Qi, self.Ri = 0.5 * (self.Qi + self.Qi.T), 0.5 * (self.Ri + self.Ri.T)
        x, u, xn = ca.SX.sym("x", n), ca.SX.sym("u", p), ca.SX.sym("xn", n)
        y, md, mm = ca.SX.sym("y", m), ca.SX.sym("md"), ca.SX.sym("mm")
        # the model's numbers (dt, weights, physical parameters) and Q⁻¹, R⁻¹ are inputs, filled once
        # below: the generated code depends on the architecture only, and a new model of it is no
        # new compilation (`estimators.parametric`)
        symbolic = symbolic_model(mhe.model, mhe.dt)
        f, hx = symbolic.model.step(x, u, symbolic.dt), symbolic.model.h(x, u)
        # diagonal Q and R (the systems' own) enter as their diagonals: a dense n×n input would add n²
        # multiplications per node where constants folded to n, and slow every gradient sweep
        diagonal = not (np.count_nonzero(self.Qi - np.diag(np.diag(self.Qi)))
                        or np.count_nonzero(self.Ri - np.diag(np.diag(self.Ri))))
        if diagonal:
            Qi, Ri = ca.SX.sym("Qi", n), ca.SX.sym("Ri", m)
            weights = (np.diag(self.Qi)[None], np.diag(self.Ri)[None])
            lam_w = Qi * (md * (xn - f))      # Q⁻¹ w_i (0 on the last node and padding)
            v = mm * (y - hx)
            lam_v = Ri * v
        else:
            Qi, Ri = ca.SX.sym("Qi", n, n), ca.SX.sym("Ri", m, m)
            weights = (self.Qi.T, self.Ri.T)   # buffers are column-major: numpy sees the transpose
            lam_w = Qi @ (md * (xn - f))
            v = mm * (y - hx)
            lam_v = Ri @ v
        # ∂cost/∂x_i (half of it) without the arrival and the Q⁻¹w_{i-1} terms: -Fᵢᵀ Q⁻¹wᵢ - Hᵢᵀ R⁻¹vᵢ
        grad = -ca.jtimes(f, x, lam_w, True) - ca.jtimes(hx, x, lam_v, True)
        theta = symbolic.params
        node = ca.Function("lrn_node", [x, u, xn, y, md, mm, theta, Qi, Ri], [lam_w, grad])
        F, H = ca.densify(ca.jacobian(f, x)), ca.densify(ca.jacobian(hx, x))
        jac = ca.Function("lrn_jac", [x, u, theta], [f, F, H])
        # one node with h too: gn.c calls it per node and forms the next gradient from its outputs
        jac1 = ca.Function("lrn_jac1", [x, u, theta], [f, F, H, hx])
        self.linear = not (ca.depends_on(F, x) or ca.depends_on(H, x))
        # one exact step solves a quadratic problem; the new node's H is borrowed from its predecessor,
        # exact only when H does not depend on u
        self.one_step = self.linear and not ca.depends_on(H, u)
        # mapped over the nodes; θ, Q⁻¹ and R⁻¹ are the same for every node (not repeated)
        # everything above is derived from f and h by this code with Lmax and `diagonal` as its only
        # choices: the key that lets a second MHE of this model in this process skip code generation
        key = model_key(ca.Function("lrn_model", [x, u, theta], [f, hx]), "mhe_gn", self.Lmax, diagonal)
        self.sweep, self.jac2, self.jac_all, self.jac1 = compiled(
            [mapped(node, "lrn_sweep", self.Lmax, (6, 7, 8)), mapped(jac, "lrn_jac2", 2, (2,)),
             mapped(jac, "lrn_jacn", self.Lmax, (2,)), jac1], cache_dir=cache_dir, compiler=compiler, key=key)
        for fn, index in ((self.sweep, 6), (self.jac2, 2), (self.jac_all, 2), (self.jac1, 2)):
            fn.inputs[index][0] = symbolic.values
        self.sweep.inputs[7][...], self.sweep.inputs[8][...] = weights
        self.backend = self.sweep.backend
        self.linalg = BlockTridiagonal(n, m, self.Lmax, self.Qi, self.Ri, cache_dir, compiler)
        self.stats = {"solves": 0, "iterations": 0, "relinearisations": 0, "node_jacobians": 0, "ipopt_fallbacks": 0,
                      "failures": 0}
        self._mask_length = -1
        fs, Fs, Hs = np.zeros((2, n)), np.zeros((2, n, n)), np.zeros((2, m, n))
        self._jac2_out = (fs, Fs, Hs, ((fs[0], fs[1]), (Fs[0], Fs[1]), (Hs[0], Hs[1])))
        self._native = None
        if self.sweep.backend == "c" and self.linalg.lib is not None and max(n, m) <= 64:   # gn.c's stack arrays
            self._native = _NativeWindow(self)

    # -- evaluations ------------------------------------------------------------------------------------
    def _gradient(self, X, u_win, y_win, x_bar, P_inv):
        """The exact gradient (L, n) of half the window's cost at X (L, n)."""
        L = len(X)
        ins = self.sweep.inputs
        ins[0][:L] = X
        ins[0][L:] = X[-1]                      # padding at a valid point (masked, but must be finite)
        ins[1][:L] = u_win
        ins[1][L:] = u_win[-1]
        ins[2][:L - 1] = X[1:]
        ins[2][L - 1:] = X[-1]
        ins[3][:L] = y_win
        lam_w, grad = self.sweep()
        g = grad[:L].copy()
        g[1:] += lam_w[:L - 1]
        g[0] += P_inv @ (X[0] - x_bar)
        return g

    def _set_masks(self, L):
        if L == self._mask_length:   # constant once the window has stopped growing
            return
        self._mask_length = L
        ins = self.sweep.inputs
        ins[4][:] = 0.0
        ins[4][:L - 1] = 1.0
        ins[5][:] = 0.0
        ins[5][:L] = 1.0

    def _relinearise(self, X, u_win, F, H):
        L = len(X)
        ins = self.jac_all.inputs
        ins[0][:L], ins[0][L:] = X, X[-1]
        ins[1][:L], ins[1][L:] = u_win, u_win[-1]
        _, Ft, Ht = self.jac_all()
        n, m = self.mhe.n, self.mhe.m
        F[:L] = np.swapaxes(Ft.reshape(self.Lmax, n, n)[:L], 1, 2)
        H[:L] = np.swapaxes(Ht.reshape(self.Lmax, n, m)[:L], 1, 2)
        self.stats["relinearisations"] += 1
        self.stats["node_jacobians"] += L

    def _jac2(self, xa, ua, xb, ub):
        """f (2, n), F (2, n, n), H (2, m, n) at two points (one compiled call), each a pair of arrays
        overwritten by the next call: the same array objects every time (`_NativeWindow` keeps their
        addresses; a fresh copy per step cost more than the call)."""
        ins = self.jac2.inputs
        ins[0][0], ins[0][1], ins[1][0], ins[1][1] = xa, xb, ua, ub
        f, Ft, Ht = self.jac2()
        n, m = self.mhe.n, self.mhe.m
        fs, Fs, Hs, pairs = self._jac2_out
        fs[...] = f
        np.copyto(Fs, np.swapaxes(Ft.reshape(2, n, n), 1, 2))
        np.copyto(Hs, np.swapaxes(Ht.reshape(2, n, m), 1, 2))
        return pairs

    # -- one window -------------------------------------------------------------------------------------
    def _solve(self, X, u_win, y_win, x_bar, P_inv, F, H):
        """(X*, converged): full Gauss–Newton steps from the warm start X (L, n) (the Python loop; with a
        compiler the whole recursion runs in `gn.c`, `_NativeWindow.run`)."""
        L = len(X)
        self._set_masks(L)
        factor = self.linalg.factor(L, F, H, P_inv)
        limit = self.max_iter or 30
        last_step, first_step = None, None
        for it in range(limit):
            g = self._gradient(X, u_win, y_win, x_bar, P_inv)
            self.stats["iterations"] += 1
            dx = self.linalg.solve(factor, -g)
            step = float(np.abs(dx).max())
            if not np.isfinite(step) or (first_step is not None and step > 1e3 * first_step):
                return X, False                          # diverging: the caller falls back to IPOPT
            first_step = step if first_step is None else first_step
            X = X + dx
            if self.one_step or step <= self.tol:
                return X, True
            if last_step is not None and step < last_step and last_step <= RATE_REGIME:
                rho = step / last_step                   # asymptotic regime: trust the contraction estimate
                if rho * step / (1.0 - rho) <= self.tol:
                    return X, True
            if it + 1 < limit and (last_step is None or step > 0.2 * last_step):
                # after the first step (the new measurement moves the recent nodes by up to ~0.04 in
                # acceleration), and whenever the contraction is slow, re-linearise at the iterate: on the
                # KNODE this takes fewer gradient sweeps per window than keeping the reused Jacobians until
                # the contraction stalls, or than re-linearising before the first step too
                self._relinearise(X, u_win, F, H)
                factor = self.linalg.factor(L, F, H, P_inv)
            last_step = step
        return X, self.max_iter is not None

    # -- the recursion ----------------------------------------------------------------------------------
    def run(self, y, u, x_bar, progress=None) -> np.ndarray:
        """Estimate x̂_{k|k} for every k, the window growing to horizon + 1 nodes and then sliding.

        Called by `MHE.run`, which checks the shapes.

        Parameters
        ----------
        y : (T, m) array
            Measurements, one row per step.
        u : (T, p) array
            Inputs, one row per step.
        x_bar : (n,) array
            Prior guess of the first state (the arrival x̄ at k = 0).
        progress : callable, optional
            Called with k after each step.

        Returns
        -------
        (T, n) array
            The last node of each window's solution.

        Warns
        -----
        NumericalWarning
            Some windows did not converge (even after the IPOPT fallback).  The count comes from `stats`, which
            accumulates over calls.
        """
        if self._native is not None:
            estimates = self._native.run(y, u, x_bar, progress)
        else:
            estimates = self._run(y, u, x_bar, progress)
        if self.stats["failures"]:
            warnings.warn(f"MHE Gauss-Newton: {self.stats['failures']} of {self.stats['solves']} windows did not "
                          "converge", NumericalWarning, stacklevel=3)
        return estimates

    def _run(self, y, u, x_bar, progress):
        """`run` in Python (CasADi's interpreter, no compiler); `gn.c`'s lrn_mhe_run is the same loop."""
        mhe = self.mhe
        n, m, N, T = mhe.n, mhe.m, mhe.horizon, len(y)
        F, H = np.zeros((self.Lmax, n, n)), np.zeros((self.Lmax, m, n))
        P_arrival = mhe.P0.copy()
        P_inv = np.linalg.inv(P_arrival)
        window = np.zeros((self.Lmax, n))   # the window's states, shifted in place
        _, Fs, Hs = self._jac2(x_bar, u[0], x_bar, u[0])
        F[0], H[0] = Fs[0], Hs[0]
        window[0] = x_bar
        estimates = np.empty((T, n))
        for k in range(T):
            start = max(0, k - N)
            L = k - start + 1
            X, ok = self._solve(window[:L], u[start:k + 1], y[start:k + 1], x_bar, P_inv, F, H)
            self.stats["solves"] += 1
            if not ok and self.max_iter is None:
                # Gauss–Newton drops the dynamics' curvature weighted by Q⁻¹w; with a very curved model
                # and stiff Q it can cycle.  IPOPT's line search then solves this window (same problem).
                X, ok = mhe.solve_window_ipopt(X, u[start:k + 1], y[start:k + 1], x_bar, P_inv)
                self.stats["ipopt_fallbacks"] += 1
            self.stats["failures"] += int(not ok)
            window[:L] = X
            estimates[k] = X[-1]
            # Jacobians at the solution's first node (arrival update) and last node (its edge to the
            # next node, and the prediction x_{k+1} = f(x̂_k) that starts the next window)
            fs, Fs, Hs = self._jac2(X[0], u[start], X[-1], u[k])
            F[L - 1], H[L - 1] = Fs[1], Hs[1]
            slides = k + 1 - N > start
            if slides:
                if mhe.arrival == "ekf":
                    P_arrival[...] = _ekf_update(Fs[0], Hs[0], P_arrival, mhe.Q, mhe.R)
                    P_inv[...] = np.linalg.inv(P_arrival)
                x_bar = mhe.arrival_mean(window[1], estimates[start], u[start])   # MHE._shift
                window[:L - 1] = window[1:L]   # numpy copies overlapping slices correctly
                window[L - 1] = fs[1]
                F[:L - 1], H[:L - 1] = F[1:L], H[1:L]
                F[L - 1], H[L - 1] = Fs[1], Hs[1]   # the new node: linearised at its predecessor until solved
            else:
                window[L] = fs[1]
                F[L], H[L] = Fs[1], Hs[1]
            if progress:
                progress(k)
        return estimates


class _Fn(ctypes.Structure):
    """gn.c's lrn_fn: a compiled CasADi function and its argument and work arrays."""

    _fields_ = [("fn", ctypes.c_void_p), ("arg", ctypes.c_void_p), ("res", ctypes.c_void_p),
                ("iw", ctypes.c_void_p), ("w", ctypes.c_void_p), ("mem", ctypes.c_longlong)]


class _Problem(ctypes.Structure):
    """gn.c's lrn_gn: sizes, stopping rule, functions, matrices and scratch of one window solver."""

    _fields_ = [*[(name, ctypes.c_int) for name in ("n", "m", "p", "Lmax", "limit", "one_step", "bounded")],
                ("tol", ctypes.c_double), ("rate_regime", ctypes.c_double),
                ("sweep", _Fn), ("jac", _Fn),
                *[(name, ctypes.c_void_p) for name in ("Qi", "Ri", "Pinv", "R", "C", "work", "g", "dx", "f", "h")],
                *[(name, ctypes.c_longlong) for name in ("iterations", "relinearisations", "node_jacobians")]]


class _Run(ctypes.Structure):
    """gn.c's lrn_mhe: one run of the recursion (sequence, window, arrival, scratch, resume point)."""

    _fields_ = [*[(name, ctypes.c_int) for name in ("T", "N", "ekf", "k_end", "smoothing")],
                *[(name, ctypes.c_void_p) for name in ("y", "u", "estimates", "X", "x_bar", "F", "H", "P", "Q", "R",
                                                       "ekf_work", "fa", "Fa", "Ha", "fb", "Fb", "Hb")],
                *[(name, ctypes.c_int) for name in ("k", "stage", "ok")],
                ("failures", ctypes.c_longlong), ("fallbacks", ctypes.c_longlong)]


class _NativeWindow:
    """`GaussNewtonWindowSolver.run` in C (`gn.c`: lrn_mhe_run around lrn_gn_window, the same loop, the
    same stopping rule), back in Python only for a window IPOPT must solve.

    Why: driving each window from Python costs as much as its arithmetic (numpy and ctypes overhead on
    every call), and the recursion around the windows, left in Python, would still be a sizeable share of a
    flight's MHE run."""

    def __init__(self, gn: GaussNewtonWindowSolver):
        self.gn, mhe, linalg = gn, gn.mhe, gn.linalg
        n, m, Lmax = mhe.n, mhe.m, gn.Lmax
        self.X, self.x_bar = np.zeros((Lmax, n)), np.zeros(n)
        self.g, self.dx, self.f = np.zeros((Lmax, n)), np.zeros((Lmax, n)), np.zeros((Lmax, n))
        self.h = np.zeros((Lmax, m))
        self.ekf_work = np.zeros(3 * n * n + 2 * n * m + 2 * m ** 2)   # gn.c lrn_ekf_arrival's layout
        self.scratch = {name: np.zeros(shape) for name, shape in (("fa", n), ("Fa", (n, n)), ("Ha", (m, n)),
                                                                  ("fb", n), ("Fb", (n, n)), ("Hb", (m, n)))}
        self.Q, self.R = np.ascontiguousarray(mhe.Q, dtype=float), np.ascontiguousarray(mhe.R, dtype=float)
        problem = _Problem(n=n, m=m, p=mhe.p, Lmax=Lmax, limit=gn.max_iter or 30, one_step=int(gn.one_step),
                           bounded=int(gn.max_iter is not None), tol=gn.tol, rate_regime=RATE_REGIME,
                           sweep=_Fn(*gn.sweep.pointers()), jac=_Fn(*gn.jac1.pointers()),
                           Qi=_address(linalg.Qi), Ri=_address(linalg.Ri), Pinv=_address(linalg._pinv),
                           R=_address(linalg.R), C=_address(linalg.C), work=_address(linalg.work),
                           g=_address(self.g), dx=_address(self.dx), f=_address(self.f), h=_address(self.h))
        self.problem = problem
        self._run = linalg.lib.lrn_mhe_run
        self._run.argtypes, self._run.restype = [ctypes.c_void_p] * 2, ctypes.c_int
        self._ekf = linalg.lib.lrn_ekf_arrival
        self._ekf.argtypes = [ctypes.c_int] * 2 + [ctypes.c_void_p] * 7
        self._ekf.restype = ctypes.c_int

    def run(self, y, u, x_bar, progress=None) -> np.ndarray:
        """Estimates (T, n), as `GaussNewtonWindowSolver.run`; ``progress`` makes it return to Python after
        every step to call it."""
        gn, mhe, problem = self.gn, self.gn.mhe, self.problem
        n, m, N, T = mhe.n, mhe.m, mhe.horizon, len(y)
        y, u = np.ascontiguousarray(y, dtype=float), np.ascontiguousarray(u, dtype=float).reshape(T, mhe.p)
        F, H = np.zeros((gn.Lmax, n, n)), np.zeros((gn.Lmax, m, n))
        P = np.array(mhe.P0, dtype=float)
        P_inv = gn.linalg._pinv   # gn.c's Pinv: the window solver reads it, the arrival update writes it
        P_inv[...] = np.linalg.inv(P)
        _, Fs, Hs = gn._jac2(x_bar, u[0], x_bar, u[0])
        F[0], H[0] = Fs[0], Hs[0]
        self.X[0], self.x_bar[...] = x_bar, x_bar
        estimates = np.empty((T, n))
        arrays = {"y": y, "u": u, "estimates": estimates, "X": self.X, "x_bar": self.x_bar, "F": F, "H": H, "P": P,
                  "Q": self.Q, "R": self.R, "ekf_work": self.ekf_work, **self.scratch}
        run = _Run(T=T, N=N, ekf=int(mhe.arrival == "ekf"), smoothing=int(mhe.arrival_update == "smoothing"), k=0,
                   stage=0,
                   **{name: _address(a) for name, a in arrays.items()})
        problem.iterations = problem.relinearisations = problem.node_jacobians = 0
        try:
            while run.k < T:
                run.k_end = T if progress is None else run.k + 1
                while (status := self._run(ctypes.addressof(problem), ctypes.addressof(run))) == 1:
                    # Gauss–Newton did not converge on window k (see `run`): IPOPT solves it, same problem
                    k = run.k
                    start = max(0, k - N)
                    L = k - start + 1
                    X, ok = mhe.solve_window_ipopt(self.X[:L].copy(), u[start:k + 1], y[start:k + 1],
                                                   self.x_bar.copy(), P_inv.copy())
                    self.X[:L], run.ok = X, int(ok)
                if status == -1:
                    raise RuntimeError("compiled CasADi function returned an error")
                if status == 2:
                    raise np.linalg.LinAlgError("MHE arrival covariance singular")
                if status < -1:
                    raise np.linalg.LinAlgError(f"MHE Gauss-Newton matrix not positive definite (row {-status - 3})")
                if progress:
                    progress(run.k - 1)
        finally:
            stats = gn.stats
            stats["solves"] += run.k
            stats["iterations"] += problem.iterations
            stats["relinearisations"] += problem.relinearisations
            stats["node_jacobians"] += problem.node_jacobians
            stats["ipopt_fallbacks"] += run.fallbacks
            stats["failures"] += run.failures
            gn._mask_length = -1   # gn.c wrote the masks: the Python loop's cache of them is stale
        return estimates

    def arrival(self, F, H, P, P_inv):
        """`_ekf_update` of P (n, n) in place and P_inv := P⁻¹, in C (F (n, n), H (m, n) C-contiguous)."""
        mhe = self.gn.mhe
        if self._ekf(mhe.n, mhe.m, _address(F), _address(H), _address(P), _address(self.Q), _address(self.R),
                     _address(P_inv), _address(self.ekf_work)):
            raise np.linalg.LinAlgError("MHE arrival covariance singular")


def _ekf_update(F, H, P, Q, R):
    """The arrival weight's EKF recursion (the same formula as the IPOPT version's)."""
    S = H @ P @ H.T + R
    P = P - P @ H.T @ np.linalg.solve(S, H @ P)
    P = F @ P @ F.T + Q
    return 0.5 * (P + P.T)
