/* One MHE window's Gauss-Newton iterations in C (estimators/mhe_gn.py, `_solve` is the same loop in
 * Python, kept for CasADi's interpreter).  Compiled together with btd.c.
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
    int n, m, Lmax, limit, one_step, bounded;  /* bounded: max_iter was given (stop without failing) */
    double tol, rate_regime;
    lrn_fn sweep;   /* inputs x, u, xn, y, md, mm (Lmax each); outputs lam_w, grad (Lmax, n) */
    lrn_fn jac;     /* inputs x, u (Lmax); outputs f (Lmax, n), F' (Lmax, n, n), H' (Lmax, n, m) */
    const double *Qi, *Ri;
    double *Pinv, *R, *C, *work;  /* btd.c's factor storage */
    double *g, *dx;               /* (Lmax, n) scratch */
    long long iterations, relinearisations;
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

/* F (Lmax, n, n), H (Lmax, m, n) row-major from the jac function at X; u is already in its input */
static int relinearise(lrn_gn *p, int L, const double *X, double *F, double *H) {
    int n = p->n, m = p->m;
    pad_rows(n, L, p->Lmax, X, p->jac.arg[0]);
    if (call(&p->jac)) return -1;
    const double *Ft = p->jac.res[1], *Ht = p->jac.res[2];
    for (int i = 0; i < L; ++i) {
        for (int r = 0; r < n; ++r)
            for (int c = 0; c < n; ++c) F[(i * n + r) * n + c] = Ft[(i * n + c) * n + r];
        for (int r = 0; r < m; ++r)
            for (int c = 0; c < n; ++c) H[(i * m + r) * n + c] = Ht[(i * n + c) * m + r];
    }
    p->relinearisations++;
    return 0;
}

/* Full Gauss-Newton steps from the warm start X (L, n), in place.  Returns 1 converged, 0 not converged
 * (diverging or out of iterations: the caller hands the window to IPOPT), -1 a CasADi function failed,
 * -2 - k the matrix is not positive definite (k from lrn_btd_factor). */
int lrn_gn_window(lrn_gn *p, int L, double *X, const double *xbar, double *F, double *H) {
    int n = p->n, N = L * n;
    int info = lrn_btd_factor(n, p->m, L, F, H, p->Qi, p->Ri, p->Pinv, p->R, p->C, p->work);
    if (info) return -2 - info;
    double last_step = -1.0, first_step = -1.0;
    for (int it = 0; it < p->limit; ++it) {
        if (gradient(p, L, X, xbar)) return -1;
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
            info = lrn_btd_factor(n, p->m, L, F, H, p->Qi, p->Ri, p->Pinv, p->R, p->C, p->work);
            if (info) return -2 - info;
        }
        last_step = step;
    }
    return p->bounded;
}
