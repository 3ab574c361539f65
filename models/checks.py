"""Validation at the estimators' boundary: wrong shapes, NaN and broken covariances fail loudly here."""
from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from learnest.errors import InvalidInput


def check_sequence(name: str, array: ArrayLike, rows: int | None = None, cols: int | None = None) -> np.ndarray:
    """A (T, k) finite float array; a 1-D array is read as one channel.

    Raises
    ------
    InvalidInput
        If it is not 2-D, has the wrong number of rows or columns, or holds NaN/inf.
    """
    arr = np.asarray(array, dtype=float)
    if arr.ndim == 1 and cols in (None, 1):
        arr = arr[:, None]
    if arr.ndim != 2:
        raise InvalidInput(f"{name} must be 2-D (time, channels), got shape {arr.shape}")
    if rows is not None and arr.shape[0] != rows:
        raise InvalidInput(f"{name} has {arr.shape[0]} rows, expected {rows}")
    if cols is not None and arr.shape[1] != cols:
        raise InvalidInput(f"{name} has {arr.shape[1]} columns, expected {cols}")
    if not np.all(np.isfinite(arr)):
        bad = int(np.argwhere(~np.isfinite(arr))[0, 0])
        raise InvalidInput(f"{name} contains NaN or infinite values (first at row {bad})")
    return arr


def check_inputs(u: ArrayLike | None, rows: int, cols: int) -> np.ndarray:
    """Inputs as a (rows, cols) array; None (or an empty array) means "no inputs" for a model with none."""
    if u is None or (np.size(u) == 0 and cols == 0):
        if cols:
            raise InvalidInput(f"u is required: the model has {cols} input(s)")
        return np.zeros((rows, 0))
    u = np.asarray(u, dtype=float)
    if u.ndim == 1 and cols == 1:
        u = u[:, None]
    return check_sequence("u", u, rows=rows, cols=cols)


def check_vector(name: str, vector: ArrayLike, size: int) -> np.ndarray:
    """``vector`` flattened to a finite float array of shape (size,); else `InvalidInput`."""
    vec = np.asarray(vector, dtype=float).reshape(-1)
    if vec.shape != (size,):
        raise InvalidInput(f"{name} must have {size} entries, got shape {np.shape(vector)}")
    if not np.all(np.isfinite(vec)):
        raise InvalidInput(f"{name} contains NaN or infinite values")
    return vec


def check_covariance(name: str, matrix: ArrayLike, size: int, allow_singular: bool = False) -> np.ndarray:
    """Square, finite, symmetric and positive (semi-)definite; the message says which test failed."""
    mat = np.asarray(matrix, dtype=float)
    if mat.shape != (size, size):
        raise InvalidInput(f"{name} must be {size}x{size}, got shape {mat.shape}")
    if not np.all(np.isfinite(mat)):
        raise InvalidInput(f"{name} contains NaN or infinite values")
    if not np.allclose(mat, mat.T, rtol=1e-8, atol=1e-12):
        raise InvalidInput(f"{name} is not symmetric")
    smallest = np.linalg.eigvalsh(mat).min()
    if smallest < -1e-12 * max(1.0, np.abs(mat).max()) or (not allow_singular and smallest <= 0):
        kind = "semi-definite" if allow_singular else "definite"
        raise InvalidInput(f"{name} is not positive {kind} (smallest eigenvalue {smallest:.3g})")
    return mat


def check_dt(dt: float) -> float:
    """``dt`` (s) as a float if it is finite and positive; else `InvalidInput`."""
    if not (np.isfinite(dt) and dt > 0):
        raise InvalidInput(f"dt must be a positive finite number of seconds, got {dt}")
    return float(dt)
