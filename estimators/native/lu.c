/* Dense LU solve shared by gn.c (the MHE's arrival update) and ukf.c (the UKF's innovation covariance):
 * compiled in front of each (`mhe_gn.BlockTridiagonal`, `ukf_native.load_library`). */
#include <math.h>

/* X (n, k) := A^{-1} X by Gaussian elimination with partial pivoting, numpy's LU route (A (n, n)
 * overwritten; row-major).  Why: S and P are symmetric positive definite in exact arithmetic, but rounding
 * can make them indefinite; Cholesky then fails where np.linalg.solve/inv would still succeed, and an
 * evaluation must not end on a matrix numpy accepts.  Returns 0, or 1 on an exactly zero pivot (singular:
 * numpy raises then too). */
static int lu_solve(int n, int k, double *A, double *X) {
    for (int c = 0; c < n; ++c) {
        int piv = c;
        for (int r = c + 1; r < n; ++r)
            if (fabs(A[r * n + c]) > fabs(A[piv * n + c])) piv = r;
        if (A[piv * n + c] == 0.0) return 1;
        if (piv != c) {
            for (int j = 0; j < n; ++j) { double t = A[c * n + j]; A[c * n + j] = A[piv * n + j]; A[piv * n + j] = t; }
            for (int j = 0; j < k; ++j) { double t = X[c * k + j]; X[c * k + j] = X[piv * k + j]; X[piv * k + j] = t; }
        }
        for (int r = c + 1; r < n; ++r) {
            double f = A[r * n + c] / A[c * n + c];
            if (f == 0.0) continue;
            for (int j = c; j < n; ++j) A[r * n + j] -= f * A[c * n + j];
            for (int j = 0; j < k; ++j) X[r * k + j] -= f * X[c * k + j];
        }
    }
    for (int r = n - 1; r >= 0; --r)
        for (int j = 0; j < k; ++j) {
            double t = X[r * k + j];
            for (int q = r + 1; q < n; ++q) t -= A[r * n + q] * X[q * k + j];
            X[r * k + j] = t / A[r * n + r];
        }
    return 0;
}
