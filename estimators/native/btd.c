/* Block-tridiagonal Cholesky for the MHE's Gauss-Newton matrix (estimators/mhe_gn.py).
 *
 * The matrix of an L-node window has diagonal blocks
 *     D_i = H_i' Ri H_i + [i < L-1] F_i' Qi F_i + [i > 0] Qi + [i == 0] Pinv
 * and upper off-diagonal blocks B_i = -F_i' Qi (block row i, block column i+1).  It is factored as
 * U'U with U block upper bidiagonal: U_ii = R_i (upper triangular, R_i'R_i = D_i - C_{i-1}'C_{i-1}) and
 * U_{i,i+1} = C_i = R_i^{-T} B_i.  That is the Riccati recursion of the window: O(L n^3) flops, no fill,
 * and ~1 us per block for n = 9, where LAPACK's dpbtrf spends most of its time in blocking overhead.
 * All arrays are row-major (numpy C order): F (L,n,n), H (L,m,n), R and C (L,n,n).
 * Built with -DLRN_N=n -DLRN_M=m (one library per model size) the sizes are compile-time constants: the
 * compiler can unroll the 9x9 loops (factor for L = 21, n = 9, m = 6: 107-111 -> 60-106 us in a noisy
 * side-by-side run at load ~3; not worse).
 */
#include <math.h>
#include <string.h>

/* R (upper) with R'R = A, in place of A's upper triangle; returns 0 or the failing column + 1 */
static int chol_upper(int n, double *A) {
    for (int j = 0; j < n; ++j) {
        double s = A[j * n + j];
        for (int k = 0; k < j; ++k) s -= A[k * n + j] * A[k * n + j];
        if (!(s > 0.0)) return j + 1;
        double r = sqrt(s);
        A[j * n + j] = r;
        for (int c = j + 1; c < n; ++c) {
            double t = A[j * n + c];
            for (int k = 0; k < j; ++k) t -= A[k * n + j] * A[k * n + c];
            A[j * n + c] = t / r;
        }
    }
    for (int r = 1; r < n; ++r)
        for (int c = 0; c < r; ++c) A[r * n + c] = 0.0;
    return 0;
}

/* X := R^{-T} X for an upper R (n,n) and X (n,k): forward substitution with R' */
static void solve_rt(int n, int k, const double *R, double *X) {
    for (int i = 0; i < n; ++i) {
        for (int c = 0; c < k; ++c) {
            double t = X[i * k + c];
            for (int p = 0; p < i; ++p) t -= R[p * n + i] * X[p * k + c];
            X[i * k + c] = t / R[i * n + i];
        }
    }
}

/* x := R^{-1} x for an upper R: back substitution */
static void solve_r(int n, const double *R, double *x) {
    for (int i = n - 1; i >= 0; --i) {
        double t = x[i];
        for (int p = i + 1; p < n; ++p) t -= R[i * n + p] * x[p];
        x[i] = t / R[i * n + i];
    }
}

/* out (n,n) += A' W A for A (r,n), W (r,r); work holds r*n doubles.  Zeros are skipped: W is usually
 * diagonal, H a selection and a prior's F a sparse kinematic chain (the prior MHE's factor is ~4x faster) */
static void add_atwa(int r, int n, const double *A, const double *W, double *out, double *work) {
    memset(work, 0, sizeof(double) * r * n);
    for (int i = 0; i < r; ++i)
        for (int p = 0; p < r; ++p) {
            double w = W[i * r + p];
            if (w == 0.0) continue;
            for (int c = 0; c < n; ++c) work[i * n + c] += w * A[p * n + c];      /* W A */
        }
    for (int p = 0; p < r; ++p)
        for (int a = 0; a < n; ++a) {
            double v = A[p * n + a];
            if (v == 0.0) continue;
            for (int b = 0; b < n; ++b) out[a * n + b] += v * work[p * n + b];
        }
}

int lrn_btd_factor(int n, int m, int L, const double *F, const double *H, const double *Qi,
                   const double *Ri, const double *Pinv, double *R, double *C, double *work) {
#ifdef LRN_N
    n = LRN_N;
    m = LRN_M;
#endif
    int nn = n * n;
    for (int i = 0; i < L; ++i) {
        double *D = R + i * nn;
        memset(D, 0, sizeof(double) * nn);
        add_atwa(m, n, H + i * m * n, Ri, D, work);
        if (i < L - 1) add_atwa(n, n, F + i * nn, Qi, D, work);
        for (int p = 0; p < nn; ++p) D[p] += (i > 0 ? Qi[p] : Pinv[p]);
        if (i > 0) {                                              /* D -= C_{i-1}' C_{i-1} */
            const double *Cp = C + (i - 1) * nn;
            for (int a = 0; a < n; ++a)
                for (int b = a; b < n; ++b) {
                    double t = 0.0;
                    for (int p = 0; p < n; ++p) t += Cp[p * n + a] * Cp[p * n + b];
                    D[a * n + b] -= t;
                }
        }
        int info = chol_upper(n, D);
        if (info) return i * n + info;
        if (i < L - 1) {                                          /* C_i = R_i^{-T} (-F_i' Qi) */
            double *Ci = C + i * nn;
            /* work still holds Qi F_i from add_atwa above, and F_i' Qi = (Qi F_i)' (Qi symmetric) */
            for (int a = 0; a < n; ++a)
                for (int b = 0; b < n; ++b) Ci[a * n + b] = -work[b * n + a];
            solve_rt(n, n, D, Ci);
        }
    }
    return 0;
}

/* b (L*n) := A^{-1} b with A = U'U from lrn_btd_factor */
void lrn_btd_solve(int n, int L, const double *R, const double *C, double *b) {
#ifdef LRN_N
    n = LRN_N;
#endif
    int nn = n * n;
    for (int i = 0; i < L; ++i) {                                 /* U' z = b */
        double *bi = b + i * n;
        if (i > 0) {
            const double *Cp = C + (i - 1) * nn, *zp = b + (i - 1) * n;
            for (int a = 0; a < n; ++a) {
                double t = 0.0;
                for (int p = 0; p < n; ++p) t += Cp[p * n + a] * zp[p];
                bi[a] -= t;
            }
        }
        solve_rt(n, 1, R + i * nn, bi);
    }
    for (int i = L - 1; i >= 0; --i) {                            /* U x = z */
        double *bi = b + i * n;
        if (i < L - 1) {
            const double *Ci = C + i * nn, *xn = b + (i + 1) * n;
            for (int a = 0; a < n; ++a) {
                double t = 0.0;
                for (int p = 0; p < n; ++p) t += Ci[a * n + p] * xn[p];
                bi[a] -= t;
            }
        }
        solve_r(n, R + i * nn, bi);
    }
}
