"""One exception hierarchy for the whole package.

Every error a caller can act on is a `LearnestError` that carries its HTTP status, so the API, the web
pages and the CLI each need exactly one handler (mlflow's `MlflowException` habit): the API answers
`status` with ``{"detail": message}``, the web pages show the message on the page, the CLI prints it on
one line and exits 2.  Anything else is a bug and surfaces as such (500 / traceback).

Numerical trouble that does not stop the computation (a solver that did not converge, a covariance that
had to be repaired) is reported with `NumericalWarning`, never silently.
"""
from __future__ import annotations


class LearnestError(Exception):
    """Base class of every error learnest raises on purpose; ``status`` is its HTTP status."""

    status: int = 500


class InvalidInput(LearnestError, ValueError):
    """Input the caller can fix (a corrupt log, a bad parameter, an unusable request): HTTP 422."""

    status = 422


class NotFound(LearnestError, LookupError):
    """An id, name, version, alias or file that does not exist: HTTP 404."""

    status = 404


class Conflict(LearnestError):
    """A valid request that the resource's current state does not allow: HTTP 409."""

    status = 409


class NumericalWarning(RuntimeWarning):
    """A numerical step went wrong but the result is still returned (solver not converged, covariance
    repaired); the message says what and where."""


__all__ = ["Conflict", "InvalidInput", "LearnestError", "NotFound", "NumericalWarning"]
