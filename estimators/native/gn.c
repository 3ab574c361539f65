/* One MHE window's Gauss-Newton iterations in C (estimators/mhe_gn.py, `_solve` is the same loop in
 * Python, kept for CasADi's interpreter).  Compiled together with lu.c and btd.c.
 *
 * Why: in Python each iteration paid ~150-300 us of numpy and ctypes overhead around ~150 us of
 * arithmetic (the gradient sweep, the solve); here the loop calls the compiled CasADi functions through
 * function pointers handed over from Python (`codegen.CompiledFunction.pointers`) and costs nothing
 * beyond their arithmetic.
 *
 * Buffers follow CasADi's column-major layout seen from numpy: a mapped (n, Lmax) input is Lmax rows of n.
 */
#include <math.h>
#include <string.h>

typedef int (*lrn_casadi_fn)(const double **arg, double **res, long long *iw, double *w, int mem);

/* a compiled CasADi function with its argument and work arrays (filled by Python once) */
typedef struct {
    lrn_casadi_fn fn;
    double **arg;   /* arg[i] -> input buffer i */
    double **res;   /* res[i] -> output buffer i */
    long long *iw;
    double *w;
    long long mem;
} lrn_fn;

typedef struct {
    int n, m, p, Lmax, limit, one_step, bounded;  /* bounded: max_iter was given (stop without failing) */
    double tol, rate_regime;
    lrn_fn sweep;   /* inputs x, u, xn, y, md, mm (Lmax each); outputs lam_w, grad (Lmax, n) */
    lrn_fn jac;     /* one node: inputs x (n), u (p); outputs f (n), F' (n, n), H' (n, m), h (m) */
    const double *Qi, *Ri;
    double *Pinv, *R, *C, *work;  /* btd.c's factor storage */
    double *g, *dx;               /* (Lmax, n) scratch */
    double *f, *h;                /* f(x_i) (Lmax, n) and h(x_i) (Lmax, m) at the last re-linearisation */
    long long iterations, relinearisations, node_jacobians;
} lrn_gn;

int lrn_btd_factor(int n, int m, int L, const double *F, const double *H, const double *Qi,
                   const double *Ri, const double *Pinv, double *R, double *C, double *work);
void lrn_btd_solve(int n, int L, const double *R, const double *C, double *b);

static int call(const lrn_fn *f) {
    return f->fn((const double **)f->arg, f->res, f->iw, f->w, (int)f->mem);
}

/* rows [0, L) of `dst` (Lmax, n) from `src`, rows [L, Lmax) repeat src's last row (masked padding, finite) */
static void pad_rows(int n, int L, int Lmax, const double *src, double *dst) {
    memcpy(dst, src, sizeof(double) * L * n);
    for (int i = L; i < Lmax; ++i) memcpy(dst + i * n, src + (L - 1) * n, sizeof(double) * n);
}

/* the exact gradient (half the cost's) at X into p->g; u, y and the masks are already in sweep's inputs */
static int gradient(lrn_gn *p, int L, const double *X, const double *xbar) {
    int n = p->n;
    double **in = p->sweep.arg;
    pad_rows(n, L, p->Lmax, X, in[0]);
    if (L > 1) pad_rows(n, L - 1, p->Lmax, X + n, in[2]);   /* x_{i+1}: X[1:], then X[-1] */
    else pad_rows(n, 1, p->Lmax, X, in[2]);
    if (call(&p->sweep)) return -1;
    const double *lam_w = p->sweep.res[0], *grad = p->sweep.res[1];
    memcpy(p->g, grad, sizeof(double) * L * n);
    for (int i = 1; i < L; ++i)
        for (int a = 0; a < n; ++a) p->g[i * n + a] += lam_w[(i - 1) * n + a];
    for (int a = 0; a < n; ++a) {
        double t = 0.0;
        for (int b = 0; b < n; ++b) t += p->Pinv[a * n + b] * (X[b] - xbar[b]);
        p->g[a] += t;
    }
    return 0;
}

/* F[i] (n, n), H[i] (m, n) row-major for every node at X, one call per node (no padding to
 * compute); u from the sweep's input */
static int relinearise(lrn_gn *p, int L, const double *X, double *F, double *H) {
    int n = p->n, m = p->m;
    const double *Ft = p->jac.res[1], *Ht = p->jac.res[2];
    for (int i = 0; i < L; ++i) {
        memcpy(p->jac.arg[0], X + i * n, sizeof(double) * n);
        if (p->p) memcpy(p->jac.arg[1], p->sweep.arg[1] + i * p->p, sizeof(double) * p->p);
        if (call(&p->jac)) return -1;
        memcpy(p->f + i * n, p->jac.res[0], sizeof(double) * n);
        memcpy(p->h + i * m, p->jac.res[3], sizeof(double) * m);
        for (int r = 0; r < n; ++r)
            for (int c = 0; c < n; ++c) F[(i * n + r) * n + c] = Ft[c * n + r];
        for (int r = 0; r < m; ++r)
            for (int c = 0; c < n; ++c) H[(i * m + r) * n + c] = Ht[c * m + r];
    }
    p->relinearisations++;
    p->node_jacobians += L;
    return 0;
}

/* The same gradient from the Jacobians, f and h of a re-linearisation at X itself (F'λ and H'λ as
 * matrix products instead of a reverse sweep): saves one sweep per window */
static void gradient_from_jacobians(lrn_gn *p, int L, const double *X, const double *xbar,
                                    const double *F, const double *H) {
    int n = p->n, m = p->m;
    const double *y = p->sweep.arg[3];
    double *lam = p->dx, v[64], lv[64];   /* Q^{-1} w_i into dx (overwritten by the step next); m <= 64 */
    for (int i = 0; i < L; ++i) {
        double *gi = p->g + i * n;
        double *li = lam + i * n;
        for (int a = 0; a < n; ++a) gi[a] = 0.0;
        if (i < L - 1) {
            double w[64];
            for (int a = 0; a < n; ++a) w[a] = X[(i + 1) * n + a] - p->f[i * n + a];
            for (int a = 0; a < n; ++a) {
                double t = 0.0;
                for (int b = 0; b < n; ++b) t += p->Qi[a * n + b] * w[b];
                li[a] = t;
            }
            for (int r = 0; r < n; ++r)
                for (int c = 0; c < n; ++c) gi[c] -= F[(i * n + r) * n + c] * li[r];
        }
        for (int r = 0; r < m; ++r) v[r] = y[i * m + r] - p->h[i * m + r];
        for (int r = 0; r < m; ++r) {
            double t = 0.0;
            for (int b = 0; b < m; ++b) t += p->Ri[r * m + b] * v[b];
            lv[r] = t;
        }
        for (int r = 0; r < m; ++r)
            for (int c = 0; c < n; ++c) gi[c] -= H[(i * m + r) * n + c] * lv[r];
        if (i > 0)
            for (int a = 0; a < n; ++a) gi[a] += lam[(i - 1) * n + a];
    }
    for (int a = 0; a < n; ++a) {
        double t = 0.0;
        for (int b = 0; b < n; ++b) t += p->Pinv[a * n + b] * (X[b] - xbar[b]);
        p->g[a] += t;
    }
}

/* Full Gauss-Newton steps from the warm start X (L, n), in place.  Returns 1 converged, 0 not converged
 * (diverging or out of iterations: the caller hands the window to IPOPT), -1 a CasADi function failed,
 * -2 - k the matrix is not positive definite (k from lrn_btd_factor). */
int lrn_gn_window(lrn_gn *p, int L, double *X, const double *xbar, double *F, double *H) {
    int n = p->n, N = L * n;
    int info = lrn_btd_factor(n, p->m, L, F, H, p->Qi, p->Ri, p->Pinv, p->R, p->C, p->work);
    if (info) return -2 - info;
    double last_step = -1.0, first_step = -1.0;
    int linearised_here = 0;   /* F, H, f, h were just taken at this X */
    for (int it = 0; it < p->limit; ++it) {
        if (linearised_here) gradient_from_jacobians(p, L, X, xbar, F, H);
        else if (gradient(p, L, X, xbar)) return -1;
        linearised_here = 0;
        p->iterations++;
        for (int k = 0; k < N; ++k) p->dx[k] = -p->g[k];
        lrn_btd_solve(n, L, p->R, p->C, p->dx);
        double step = 0.0;
        for (int k = 0; k < N; ++k) {
            double a = fabs(p->dx[k]);
            step = (a > step || a != a) ? a : step;   /* NaN propagates */
        }
        if (!isfinite(step) || (first_step >= 0.0 && step > 1e3 * first_step)) return 0;
        if (first_step < 0.0) first_step = step;
        for (int k = 0; k < N; ++k) X[k] += p->dx[k];
        if (p->one_step || step <= p->tol) return 1;
        if (last_step >= 0.0 && step < last_step && last_step <= p->rate_regime) {
            double rho = step / last_step;   /* asymptotic regime: trust the contraction estimate */
            if (rho * step / (1.0 - rho) <= p->tol) return 1;
        }
        if (it + 1 < p->limit && (last_step < 0.0 || step > 0.2 * last_step)) {
            if (relinearise(p, L, X, F, H)) return -1;
            linearised_here = 1;
            info = lrn_btd_factor(n, p->m, L, F, H, p->Qi, p->Ri, p->Pinv, p->R, p->C, p->work);
            if (info) return -2 - info;
        }
        last_step = step;
    }
    return p->bounded;
}

/* R (m, n) := R^{-1} R for an upper R (n, n): back substitution, k columns */
static void solve_r_cols(int n, int k, const double *U, double *X) {
    for (int i = n - 1; i >= 0; --i)
        for (int c = 0; c < k; ++c) {
            double t = X[i * k + c];
            for (int q = i + 1; q < n; ++q) t -= U[i * n + q] * X[q * k + c];
            X[i * k + c] = t / U[i * n + i];
        }
}

/* The arrival weight's EKF recursion (mhe_gn._ekf_update, in place) and its inverse:
 *     P := F (P - P H' (H P H' + R)^{-1} H P) F' + Q,  symmetrised;  Pinv := P^{-1} (via Cholesky, LU
 * when Cholesky refuses an S or P that rounding made indefinite).  In numpy this was ~100-200 us per step
 * of call overhead for ~5k flops.  work: 3 n n + 2 m n + 2 m m.  Returns 0, or 1 when S or P is singular. */
int lrn_ekf_arrival(int n, int m, const double *F, const double *H, double *P, const double *Q,
                    const double *R, double *Pinv, double *work) {
#ifdef LRN_N
    n = LRN_N;
    m = LRN_M;
#endif
    double *HP = work, *S = HP + m * n, *Z = S + m * m, *T = Z + m * n, *W = T + n * n, *U = W + n * n;
    double *Sc = U + n * n;                    /* a copy of S for lu_solve when Cholesky refuses it */
    for (int i = 0; i < m; ++i)
        for (int b = 0; b < n; ++b) {
            double t = 0.0;
            for (int a = 0; a < n; ++a) t += H[i * n + a] * P[a * n + b];
            HP[i * n + b] = t;
        }
    for (int i = 0; i < m; ++i)
        for (int j = 0; j < m; ++j) {
            double t = R[i * m + j];
            for (int a = 0; a < n; ++a) t += HP[i * n + a] * H[j * n + a];
            S[i * m + j] = t;
        }
    memcpy(Sc, S, sizeof(double) * m * m);
    memcpy(Z, HP, sizeof(double) * m * n);     /* Z = S^{-1} H P */
    if (chol_upper(m, S) == 0) {
        solve_rt(m, n, S, Z);
        solve_r_cols(m, n, S, Z);
    } else if (lu_solve(m, n, Sc, Z)) {
        return 1;
    }
    for (int a = 0; a < n; ++a)                /* T = P - (H P)' Z */
        for (int b = 0; b < n; ++b) {
            double t = 0.0;
            for (int i = 0; i < m; ++i) t += HP[i * n + a] * Z[i * n + b];
            T[a * n + b] = P[a * n + b] - t;
        }
    for (int a = 0; a < n; ++a)                /* W = T F' */
        for (int c = 0; c < n; ++c) {
            double t = 0.0;
            for (int b = 0; b < n; ++b) t += T[a * n + b] * F[c * n + b];
            W[a * n + c] = t;
        }
    for (int r = 0; r < n; ++r)                /* P = F W + Q */
        for (int c = 0; c < n; ++c) {
            double t = 0.0;
            for (int a = 0; a < n; ++a) t += F[r * n + a] * W[a * n + c];
            T[r * n + c] = t + Q[r * n + c];
        }
    for (int r = 0; r < n; ++r)
        for (int c = 0; c < n; ++c) P[r * n + c] = 0.5 * (T[r * n + c] + T[c * n + r]);
    memcpy(U, P, sizeof(double) * n * n);
    for (int r = 0; r < n; ++r)
        for (int c = 0; c < n; ++c) Pinv[r * n + c] = (r == c);
    if (chol_upper(n, U) == 0) {
        solve_rt(n, n, U, Pinv);
        solve_r_cols(n, n, U, Pinv);
        return 0;
    }
    memcpy(U, P, sizeof(double) * n * n);      /* Cholesky refused P: P^{-1} by LU, as numpy's inv */
    return lu_solve(n, n, U, Pinv);
}

/* The MHE recursion over a whole sequence (mhe_gn.GaussNewtonWindowSolver.run, the same steps): per k the
 * window's data into the sweep's inputs, lrn_gn_window, the Jacobians at the solution's first and last
 * node, the arrival update and the window's shift.  Why: around the window solver, Python spent ~80 us
 * per step (two KNODE-MHE and MHE runs of a 3290-step flight: 0.55 s) on slicing, copies and ctypes
 * calls.  A window Gauss-Newton cannot solve goes back to Python (IPOPT), and the loop resumes. */
typedef struct {
    int T, N, ekf, k_end, smoothing;   /* smoothing: the arrival mean is the window's X[1] (MHE.arrival_mean) */
    const double *y, *u;        /* (T, m), (T, p) */
    double *estimates;          /* (T, n) */
    double *X, *x_bar;          /* window (Lmax, n), arrival mean (n) */
    double *F, *H;              /* node Jacobians (Lmax, n, n), (Lmax, m, n) */
    double *P;                  /* arrival covariance (n, n), updated in place; P^{-1} is the solver's Pinv */
    const double *Q, *R;
    double *ekf_work;           /* 3 n n + 2 m n + m m */
    double *fa, *Fa, *Ha;       /* f, F, H at the window's first node (n), (n, n), (m, n) */
    double *fb, *Fb, *Hb;       /* and at its last node */
    int k, stage, ok;           /* resume point; ok: Python's verdict on a window it solved */
    long long failures, fallbacks;
} lrn_mhe;

/* f, F, H (row-major) at one node with the one-node Jacobian function */
static int node_jacobian(lrn_gn *p, const double *x, const double *u, double *f, double *F, double *H) {
    int n = p->n, m = p->m;
    memcpy(p->jac.arg[0], x, sizeof(double) * n);
    if (p->p) memcpy(p->jac.arg[1], u, sizeof(double) * p->p);
    if (call(&p->jac)) return -1;
    const double *Ft = p->jac.res[1], *Ht = p->jac.res[2];
    memcpy(f, p->jac.res[0], sizeof(double) * n);
    for (int r = 0; r < n; ++r)
        for (int c = 0; c < n; ++c) F[r * n + c] = Ft[c * n + r];
    for (int r = 0; r < m; ++r)
        for (int c = 0; c < n; ++c) H[r * n + c] = Ht[c * m + r];
    return 0;
}

/* Steps r->k .. r->k_end - 1.  Returns 0 when there, 1 when window r->k needs IPOPT (Python solves X[:L],
 * sets r->ok and calls again: r->stage is 1), -1 a CasADi function failed, -2 - i the Gauss-Newton matrix
 * is not positive definite (row i - 1), 2 the arrival update met a singular matrix (a code no row index can
 * take). */
int lrn_mhe_run(lrn_gn *p, lrn_mhe *r) {
    int n = p->n, m = p->m, np_ = p->p, Lmax = p->Lmax, N = r->N;
    double *u_in = p->sweep.arg[1], *y_in = p->sweep.arg[3], *md = p->sweep.arg[4], *mm = p->sweep.arg[5];
    while (r->k < r->k_end) {
        int k = r->k, start = k > N ? k - N : 0, L = k - start + 1;
        if (r->stage == 0) {
            for (int i = 0; i < Lmax; ++i) {
                md[i] = i < L - 1 ? 1.0 : 0.0;
                mm[i] = i < L ? 1.0 : 0.0;
            }
            memcpy(y_in, r->y + (size_t)start * m, sizeof(double) * L * m);
            if (np_) {   /* the Jacobians read u from here too; padding repeats the last input */
                memcpy(u_in, r->u + (size_t)start * np_, sizeof(double) * L * np_);
                for (int i = L; i < Lmax; ++i) memcpy(u_in + i * np_, r->u + (size_t)k * np_, sizeof(double) * np_);
            }
            int status = lrn_gn_window(p, L, r->X, r->x_bar, r->F, r->H);
            if (status < 0) return status;
            if (status == 0 && !p->bounded) {
                r->stage = 1;
                r->fallbacks++;
                return 1;
            }
            r->ok = status;
        }
        r->failures += !r->ok;
        r->stage = 0;
        memcpy(r->estimates + (size_t)k * n, r->X + (L - 1) * n, sizeof(double) * n);
        /* Jacobians at the solution's first node (arrival update) and last node (its edge to the next
         * node, and the prediction x_{k+1} = f(x_k) that starts the next window) */
        if (node_jacobian(p, r->X, r->u + (size_t)start * np_, r->fa, r->Fa, r->Ha)) return -1;
        if (node_jacobian(p, r->X + (L - 1) * n, r->u + (size_t)k * np_, r->fb, r->Fb, r->Hb)) return -1;
        memcpy(r->F + (L - 1) * n * n, r->Fb, sizeof(double) * n * n);   /* the last node's edge */
        memcpy(r->H + (L - 1) * m * n, r->Hb, sizeof(double) * m * n);
        int slides = k + 1 - N > start, row = slides ? L - 1 : L;
        if (slides) {
            if (r->ekf && lrn_ekf_arrival(n, m, r->Fa, r->Ha, r->P, r->Q, r->R, p->Pinv, r->ekf_work)) return 2;
            /* the arrival mean P_{s+1|s} describes: the prediction f(x_{s|s}) from the estimate at s = start
             * (its window's end then); the smoothed X[1], the paper's, counts the window's data twice
             * (MHE._shift).  Fa and Ha, used by the update above, take the Jacobians nobody reads. */
            if (r->smoothing) memcpy(r->x_bar, r->X + n, sizeof(double) * n);
            else if (node_jacobian(p, r->estimates + (size_t)start * n, r->u + (size_t)start * np_, r->x_bar,
                                   r->Fa, r->Ha)) return -1;
            memmove(r->X, r->X + n, sizeof(double) * (L - 1) * n);
            memmove(r->F, r->F + n * n, sizeof(double) * (L - 1) * n * n);
            memmove(r->H, r->H + m * n, sizeof(double) * (L - 1) * m * n);
        }
        /* the new node: the prediction, linearised at its predecessor until solved */
        memcpy(r->X + row * n, r->fb, sizeof(double) * n);
        memcpy(r->F + row * n * n, r->Fb, sizeof(double) * n * n);
        memcpy(r->H + row * m * n, r->Hb, sizeof(double) * m * n);
        r->k = k + 1;
    }
    return 0;
}
