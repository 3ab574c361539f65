/* The UKF's whole filter loop in C (estimators/ukf.py `run_ukf`; the same algorithm as
 * ukf_filterpy.BatchedUKF, which stays the reference and the path without a compiler).
 *
 * Why: with the model's sigma-point functions already compiled, each step still paid ~0.4 ms of numpy
 * and ctypes overhead in Python (25 small array operations, an inv, two factorisations) around ~0.1 ms
 * of compiled arithmetic.  Here the loop calls the compiled, mapped CasADi functions (fx over the 2n+1
 * sigma points, hx likewise) through function pointers handed over from Python
 * (`codegen.CompiledFunction.pointers`), as gn.c does for the MHE.
 *
 * Per step, as BatchedUKF: [k > 0: sigma points from the factor L of P, fx, weighted mean and covariance
 * + Q, P := sym(P), factor] sigma points re-drawn from the factor, hx, weighted mean and covariance + R
 * (S), cross covariance, K = Pxz S^{-1} by a Cholesky solve (not an explicit inverse), x += K (y - zp),
 * P := sym(P - K S K'), factor; the innovation's log density log N(v; 0, S) from the same factor of S
 * (what noise identification maximises, `estimators.noise_identification`).  When a factorisation of P fails, the loop returns to Python, which
 * repairs P with covariance_factor.spd_factor (the same function the Python filter uses, eigenvalue
 * lift and eigen square root included) and resumes here: identical in effect, and rare.
 *
 * All matrices are row-major (numpy C order).  A mapped CasADi input (n, count) is, seen from numpy,
 * count rows of n: one sigma point per row.
 */
#include <math.h>
#include <string.h>

#define LRN_LOG_2PI 1.8378770664093453   /* log(2 pi) */

typedef int (*lrn_casadi_fn)(const double **arg, double **res, long long *iw, double *w, int mem);

typedef struct {
    lrn_casadi_fn fn;
    double **arg;
    double **res;
    long long *iw;
    double *w;
    long long mem;
} lrn_fn;

typedef struct {
    int n, m, p, count, T;
    double scale;              /* sqrt(lambda + n) */
    const double *Wm, *Wc;     /* (count) Merwe weights */
    lrn_fn fx;                 /* inputs sigmas (count, n), u (count, p), theta; output (count, n) */
    lrn_fn hx;                 /* inputs sigmas (count, n), u (count, p), theta; output (count, m) */
    const double *Q, *R;       /* (n, n), (m, m) */
    const double *y, *u;       /* (T, m), (T, p) */
    double *means, *covs, *innov;   /* outputs (T, n), (T, n, n), (T, m) */
    double *loglik;            /* output (T): log N(innovation; 0, S) per step, NaN where S needed LU */
    double *x, *P, *L;         /* state: mean (n), covariance (n, n), its factor L L' = P (n, n) */
    double *work;              /* scratch, lrn_ukf_work_size doubles */
    int k, stage;              /* where the loop stands: resume point, or where a factorisation failed */
} lrn_ukf;

int lrn_ukf_work_size(int n, int m, int count) {
    (void)count;
    return 3 * m + 3 * m * m + 2 * n * m + n;
}

static int call(const lrn_fn *f) {
    return f->fn((const double **)f->arg, f->res, f->iw, f->w, (int)f->mem);
}

/* lower L with L L' = A (A untouched, L's upper triangle zeroed); 0 or the failing column + 1 */
static int chol_lower(int n, const double *A, double *L) {
    for (int j = 0; j < n; ++j) {
        double s = A[j * n + j];
        for (int k = 0; k < j; ++k) s -= L[j * n + k] * L[j * n + k];
        if (!(s > 0.0)) return j + 1;
        double d = sqrt(s);
        L[j * n + j] = d;
        for (int i = j + 1; i < n; ++i) {
            double t = A[i * n + j];
            for (int k = 0; k < j; ++k) t -= L[i * n + k] * L[j * n + k];
            L[i * n + j] = t / d;
        }
        for (int c = j + 1; c < n; ++c) L[j * n + c] = 0.0;
    }
    return 0;
}

/* the 2n+1 points x, x + scale L[:, i], x - scale L[:, i] as rows of `out` (count, n) */
static void sigma_points(const lrn_ukf *p, double *out) {
    int n = p->n;
    memcpy(out, p->x, sizeof(double) * n);
    for (int i = 0; i < n; ++i)
        for (int a = 0; a < n; ++a) {
            double s = p->scale * p->L[a * n + i];
            out[(1 + i) * n + a] = p->x[a] + s;
            out[(1 + n + i) * n + a] = p->x[a] - s;
        }
}

/* rows of the mapped u input (count, p), all u_k */
static void fill_inputs(const lrn_ukf *p, double *dst, const double *uk) {
    if (!p->p) return;
    for (int i = 0; i < p->count; ++i) memcpy(dst + i * p->p, uk, sizeof(double) * p->p);
}

/* weighted mean (d) and covariance (d, d) + noise of points (count, d), symmetric by construction */
static void transform(const lrn_ukf *p, int d, const double *pts, const double *noise, double *mean, double *cov) {
    int count = p->count;
    for (int a = 0; a < d; ++a) {
        double t = 0.0;
        for (int i = 0; i < count; ++i) t += p->Wm[i] * pts[i * d + a];
        mean[a] = t;
    }
    for (int a = 0; a < d; ++a)
        for (int b = 0; b <= a; ++b) {
            double t = 0.0;
            for (int i = 0; i < count; ++i) t += p->Wc[i] * (pts[i * d + a] - mean[a]) * (pts[i * d + b] - mean[b]);
            cov[a * d + b] = cov[b * d + a] = t;
        }
    for (int q = 0; q < d * d; ++q) cov[q] += noise[q];
}

static void symmetrise(int n, double *P) {
    for (int a = 0; a < n; ++a)
        for (int b = 0; b < a; ++b) P[a * n + b] = P[b * n + a] = 0.5 * (P[a * n + b] + P[b * n + a]);
}

/* Run from (p->k, p->stage) to the end.  Stages of step k: 0 predict (k > 0), 1 update, 2 record.
 * Returns 0 done; 1 P (symmetrised, in p->P) could not be factored: the caller sets p->P and p->L
 * (spd_factor) and calls again, p->stage already the next stage; -1 a CasADi function failed;
 * -2 S singular. */
int lrn_ukf_run(lrn_ukf *p) {
    int n = p->n, m = p->m, count = p->count;
    double *zp = p->work;   /* work: zp (m), S, its factor, a copy (m, m each), Pxz, K' (n m each), v */
    double *S = zp + m, *Sf = S + m * m, *Sc = Sf + m * m, *Pxz = Sc + m * m, *K = Pxz + n * m;
    double *v = K + n * m;   /* the innovation y_k - zp (m), kept in work across a return to Python */
    double *wv = v + m;      /* its whitened form (m) */
    while (p->k < p->T) {
        int k = p->k;
        if (p->stage == 0) {
            if (k > 0) {
                double *sig = p->fx.arg[0];
                sigma_points(p, sig);
                fill_inputs(p, p->fx.arg[1], p->u + (k - 1) * p->p);
                if (call(&p->fx)) return -1;
                transform(p, n, p->fx.res[0], p->Q, p->x, p->P);
                symmetrise(n, p->P);   /* Q need not be symmetric to the last bit */
                p->stage = 1;
                if (chol_lower(n, p->P, p->L)) return 1;
            }
            p->stage = 1;
        }
        if (p->stage == 1) {
            double *sf = p->hx.arg[0];   /* sigmas_f, re-drawn from the current factor */
            sigma_points(p, sf);
            fill_inputs(p, p->hx.arg[1], p->u + k * p->p);
            if (call(&p->hx)) return -1;
            const double *sh = p->hx.res[0];
            transform(p, m, sh, p->R, zp, S);
            for (int a = 0; a < n; ++a)          /* Pxz = sum Wc (sf - x)(sh - zp)' */
                for (int b = 0; b < m; ++b) {
                    double t = 0.0;
                    for (int i = 0; i < count; ++i)
                        t += p->Wc[i] * (sf[i * n + a] - p->x[a]) * (sh[i * m + b] - zp[b]);
                    Pxz[a * m + b] = t;
                }
            /* K' = S^{-1} Pxz' (S symmetric) */
            for (int a = 0; a < n; ++a)
                for (int b = 0; b < m; ++b) K[b * n + a] = Pxz[a * m + b];
            int s_factored = chol_lower(m, S, Sf) == 0;
            if (s_factored) {
                for (int c = 0; c < n; ++c) {        /* column c of K': L z = b, L' x = z */
                    for (int i = 0; i < m; ++i) {
                        double t = K[i * n + c];
                        for (int q = 0; q < i; ++q) t -= Sf[i * m + q] * K[q * n + c];
                        K[i * n + c] = t / Sf[i * m + i];
                    }
                    for (int i = m - 1; i >= 0; --i) {
                        double t = K[i * n + c];
                        for (int q = i + 1; q < m; ++q) t -= Sf[q * m + i] * K[q * n + c];
                        K[i * n + c] = t / Sf[i * m + i];
                    }
                }
            } else {
                memcpy(Sc, S, sizeof(double) * m * m);
                if (lu_solve(m, n, Sc, K)) return -2;
            }
            const double *yk = p->y + k * m;
            for (int b = 0; b < m; ++b) v[b] = yk[b] - zp[b];
            double ll = NAN;
            if (s_factored) {   /* -0.5 (m log 2 pi + log det S + |Sf^-1 v|^2) */
                double quad = 0.0, logdet = 0.0;
                for (int i = 0; i < m; ++i) {
                    double t = v[i];
                    for (int q = 0; q < i; ++q) t -= Sf[i * m + q] * wv[q];
                    t /= Sf[i * m + i];
                    wv[i] = t;   /* the whitened innovation Sf^-1 v */
                    quad += t * t;
                    logdet += 2.0 * log(Sf[i * m + i]);
                }
                ll = -0.5 * (m * LRN_LOG_2PI + logdet + quad);
            }
            p->loglik[k] = ll;
            for (int a = 0; a < n; ++a) {
                double t = 0.0;
                for (int b = 0; b < m; ++b) t += K[b * n + a] * v[b];
                p->x[a] += t;
            }
            /* P -= K S K' (as BatchedUKF; K S = Pxz only up to rounding) */
            for (int a = 0; a < n; ++a)            /* Pxz := K S (n, m), reusing its storage */
                for (int b = 0; b < m; ++b) {
                    double t = 0.0;
                    for (int q = 0; q < m; ++q) t += K[q * n + a] * S[q * m + b];
                    Pxz[a * m + b] = t;
                }
            for (int a = 0; a < n; ++a)
                for (int c = 0; c < n; ++c) {
                    double t = 0.0;
                    for (int b = 0; b < m; ++b) t += Pxz[a * m + b] * K[b * n + c];
                    p->P[a * n + c] -= t;
                }
            symmetrise(n, p->P);
            p->stage = 2;
            if (chol_lower(n, p->P, p->L)) return 1;
        }
        memcpy(p->means + (size_t)k * n, p->x, sizeof(double) * n);
        memcpy(p->covs + (size_t)k * n * n, p->P, sizeof(double) * n * n);
        for (int b = 0; b < m; ++b) p->innov[(size_t)k * m + b] = v[b];
        p->k = k + 1;
        p->stage = 0;
    }
    return 0;
}
