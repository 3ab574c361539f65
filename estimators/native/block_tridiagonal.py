"""The MHE window's Gauss-Newton matrix, block tridiagonal, factored and solved: compiled C (`btd.c`) or,
without a compiler, LAPACK's banded Cholesky (`estimators.mhe_gn` says why this design)."""
from __future__ import annotations

import ctypes
from pathlib import Path

import numpy as np
from scipy.linalg.lapack import dpbtrf, dpbtrs

from .codegen import load_source


class BlockTridiagonal:
    """Factor and solve the window's Gauss–Newton matrix from node Jacobians F (L, n, n), H (L, m, n);
    Qi and Ri must be symmetric (btd.c uses F'Qi = (Qi F)').

    The compiled Riccati-type recursion of `btd.c` (block Cholesky, O(L n³)); without a compiler,
    LAPACK's banded Cholesky on the same matrix (same numbers to rounding, but slower for these tiny
    blocks: dpbtrf's blocking overhead dominates, and a threaded BLAS makes it worse on a busy machine).
    """

    def __init__(self, n, m, Lmax, Qi, Ri, cache_dir=None, compiler="auto"):
        self.n, self.m, self.Lmax = n, m, Lmax
        self.Qi, self.Ri = np.ascontiguousarray(Qi), np.ascontiguousarray(Ri)
        # gn.c (the MHE's window loop) shares this library: it calls btd.c's factor and solve
        source = "\n".join(Path(__file__).with_name(name).read_text() for name in ("lu.c", "btd.c", "gn.c"))
        # sizes as compile-time constants (see btd.c); a small file, compiled in well under a second
        self.lib = load_source(source, cache_dir, compiler,
                               flags=("-O2", "-fPIC", "-shared", f"-DLRN_N={n}", f"-DLRN_M={m}"))
        self.backend = "c" if self.lib is not None else "lapack"
        if self.lib is not None:
            self.R, self.C = np.zeros((Lmax, n, n)), np.zeros((Lmax, n, n))
            self.work = np.zeros(max(n, m) * n)
            self._pinv = np.zeros((n, n))
            ptr = ctypes.c_void_p
            self._factor = self.lib.lrn_btd_factor
            self._factor.argtypes = [ctypes.c_int] * 3 + [ptr] * 8
            self._factor.restype = ctypes.c_int
            self._solve = self.lib.lrn_btd_solve
            self._solve.argtypes = [ctypes.c_int] * 2 + [ptr] * 3
            self._solve.restype = None
            self._fixed = tuple(_address(a) for a in (self.Qi, self.Ri, self._pinv, self.R, self.C, self.work))
            self._r_c = (_address(self.R), _address(self.C))
        self._bands: dict[int, tuple] = {}

    def factor(self, L, F, H, P_inv):
        """Factor the matrix of an L-node window; F (>=L, n, n), H (>=L, m, n) C-contiguous float64."""
        if self.lib is None:
            return self._factor_lapack(L, F, H, P_inv)
        self._pinv[...] = P_inv
        # raw addresses: numpy's .ctypes attribute builds an object per access (~5 µs each, 8 per call)
        info = self._factor(self.n, self.m, L, _address(F), _address(H), *self._fixed)
        if info:
            raise np.linalg.LinAlgError(f"MHE Gauss-Newton matrix not positive definite (row {info - 1})")
        return L

    def solve(self, factor, rhs):
        """rhs (L, n) -> A⁻¹ rhs (L, n)."""
        if self.lib is None:
            x, _ = dpbtrs(factor, rhs.reshape(-1, 1))
            return x.reshape(rhs.shape)
        x = np.array(rhs, dtype=float, order="C")
        self._solve(self.n, factor, self._r_c[0], self._r_c[1], _address(x))
        return x

    def _band(self, L: int):
        """(ab array, flat indices of the diagonal blocks' upper triangles and of the off-diagonal blocks)
        for LAPACK's upper band storage ab[kd + r - c, c] = A[r, c], r <= c."""
        if L not in self._bands:
            n = self.n
            N, kd = L * n, (2 * n - 1 if L > 1 else n - 1)
            a, b = np.triu_indices(n)
            blocks = np.arange(L)[:, None]
            r, c = blocks * n + a, blocks * n + b
            diag = ((kd + r - c) * N + c).ravel()
            ai, bi = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
            blocks = np.arange(L - 1)[:, None, None]
            r, c = blocks * n + ai, (blocks + 1) * n + bi
            off = ((kd + r - c) * N + c).ravel()
            self._bands[L] = (np.zeros((kd + 1, N)), diag, off, (a, b))
        return self._bands[L]

    def _factor_lapack(self, L, F, H, P_inv):
        ab, diag, off, (a, b) = self._band(L)
        QiF = self.Qi @ F[:L - 1]
        D = np.swapaxes(H[:L], 1, 2) @ (self.Ri @ H[:L])
        D[:-1] += np.swapaxes(F[:L - 1], 1, 2) @ QiF
        D[1:] += self.Qi
        D[0] += P_inv
        ab.flat[diag] = D[:, a, b].ravel()
        ab.flat[off] = -np.swapaxes(QiF, 1, 2).ravel()
        factor, info = dpbtrf(ab)
        if info:
            raise np.linalg.LinAlgError(f"MHE Gauss-Newton matrix not positive definite (dpbtrf info {info})")
        return factor


def _address(array: np.ndarray) -> int:
    if not (array.flags.c_contiguous and array.dtype == np.float64):
        raise ValueError("expected a C-contiguous float64 array")
    return array.__array_interface__["data"][0]
