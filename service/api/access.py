"""Who may call what: the scope each route needs, in one table (`RULES`), read by the request guard before
any route runs or any body is read.

Scopes nest (read < write < admin, `service.storage.tokens.SCOPES`):

- ``public``: anyone on an allowed host; only /health, the sign-in and sign-out pages and the packaged
  static files (scripts and styles every install serves alike, which the sign-in page needs).
- ``read``: every GET of the JSON API and of the pages (flights and their raw files, models and weights,
  reports, jobs, the OpenAPI schema, the manual).  LEARNEST_PUBLIC_READS=1 opens these to anyone.
- ``write``: uploads, cuts, training, evaluation, diagnosis, aliases, cancelling jobs.
- ``admin``: deletes, tokens and the audit log.

The rules apply once the server has LEARNEST_API_KEY or any token (`service.api.auth`); before that, on an
open server, every route is open as it always was.  A route missing here needs ``admin`` (a mistake fails
closed), and tests/service/api/test_access_rules.py walks every route of the app and fails for one missing here.
"""
from __future__ import annotations

import re
from functools import cache

from starlette.routing import compile_path

PUBLIC, READ, WRITE, ADMIN = "public", "read", "write", "admin"

# (method, path template) -> the scope it needs; HEAD is GET's.  First match wins: specific paths first.
RULES: dict[tuple[str, str], str] = {
    # the service itself and what any page needs to show
    ("GET", "/health"): PUBLIC,
    ("GET", "/static/{path:path}"): PUBLIC,
    ("GET", "/docs-assets/{path:path}"): PUBLIC,
    ("GET", "/vendor/plotly.min.js"): PUBLIC,
    ("GET", "/ui/signin"): PUBLIC,
    ("POST", "/ui/signin"): PUBLIC,     # checks the token it is given itself, counted by the throttle
    ("POST", "/ui/signout"): PUBLIC,    # ends the caller's own session only
    ("GET", "/openapi.json"): READ,
    ("GET", "/docs"): READ,
    ("GET", "/docs/oauth2-redirect"): READ,
    ("GET", "/redoc"): READ,
    ("GET", "/manual"): READ,
    ("GET", "/manual/{path:path}"): READ,
    ("GET", "/whoami"): READ,
    # tokens and the audit log
    ("GET", "/tokens"): ADMIN,
    ("POST", "/tokens"): ADMIN,
    ("DELETE", "/tokens/{token_id}"): ADMIN,
    ("GET", "/audit"): ADMIN,
    ("GET", "/ui/admin"): ADMIN,
    ("POST", "/ui/admin/tokens"): ADMIN,
    ("POST", "/ui/admin/tokens/{token_id}/revoke"): ADMIN,
    # flights
    ("POST", "/flights"): WRITE,
    ("POST", "/flights/batch"): WRITE,
    ("POST", "/flights/{flight_id}/cut"): WRITE,
    ("GET", "/flights"): READ,
    ("GET", "/flights/{flight_id}"): READ,
    ("GET", "/flights/{flight_id}/data"): READ,
    ("GET", "/flights/{flight_id}/raw"): READ,
    ("GET", "/flights/{flight_id}/dependents"): READ,
    ("DELETE", "/flights/{flight_id}"): ADMIN,
    # models
    ("POST", "/models"): WRITE,
    ("GET", "/models"): READ,
    ("GET", "/models/{name}"): READ,
    ("GET", "/models/{name}/versions/{version}"): READ,
    ("GET", "/models/{name}/versions/{version}/lineage"): READ,
    ("GET", "/models/{name}/versions/{version}/metadata"): READ,
    ("GET", "/models/{name}/versions/{version}/dependents"): READ,
    ("GET", "/models/{name}/versions/{version}/weights"): READ,
    ("DELETE", "/models/{name}/versions/{version}"): ADMIN,
    ("GET", "/models/{name}/aliases/{alias}"): READ,
    ("PUT", "/models/{name}/aliases/{alias}"): WRITE,
    ("DELETE", "/models/{name}/aliases/{alias}"): ADMIN,
    ("GET", "/compare"): READ,
    # jobs
    ("GET", "/jobs"): READ,
    ("GET", "/jobs/{job_id}"): READ,
    ("POST", "/jobs/{job_id}/cancel"): WRITE,
    # evaluations and diagnoses
    ("POST", "/evaluations"): WRITE,
    ("GET", "/evaluations"): READ,
    ("GET", "/evaluations/{evaluation_id}"): READ,
    ("GET", "/evaluations/{evaluation_id}/dependents"): READ,
    ("GET", "/evaluations/{evaluation_id}/estimates"): READ,
    ("GET", "/evaluations/{evaluation_id}/report.html"): READ,
    ("DELETE", "/evaluations/{evaluation_id}"): ADMIN,
    ("POST", "/diagnoses"): WRITE,
    ("GET", "/diagnoses/{diagnosis_id}"): READ,
    ("GET", "/diagnoses/{diagnosis_id}/report.html"): READ,
    # the web pages and their forms (the same scopes as the JSON routes they stand for)
    ("GET", "/"): READ,
    ("POST", "/ui/flights"): WRITE,
    ("GET", "/ui/flights/{flight_id}"): READ,
    ("POST", "/ui/flights/{flight_id}/cut"): WRITE,
    ("GET", "/ui/flights/{flight_id}/delete"): READ,     # the confirmation page only lists what would go
    ("POST", "/ui/flights/{flight_id}/delete"): ADMIN,
    ("GET", "/ui/models"): READ,
    ("POST", "/ui/models"): WRITE,
    ("GET", "/ui/models/{name}"): READ,
    ("POST", "/ui/models/{name}/aliases"): WRITE,
    ("GET", "/ui/models/{name}/versions/{version}"): READ,
    ("GET", "/ui/models/{name}/versions/{version}/delete"): READ,
    ("POST", "/ui/models/{name}/versions/{version}/delete"): ADMIN,
    ("GET", "/ui/evaluations"): READ,
    ("POST", "/ui/evaluations"): WRITE,
    ("GET", "/ui/evaluations/{evaluation_id}/delete"): READ,
    ("POST", "/ui/evaluations/{evaluation_id}/delete"): ADMIN,
    ("POST", "/ui/diagnoses"): WRITE,
    ("GET", "/ui/jobs"): READ,
    ("GET", "/ui/jobs/{job_id}"): READ,
    ("POST", "/ui/jobs/{job_id}/cancel"): WRITE,
    ("GET", "/ui/compare"): READ,
}


@cache
def _compiled() -> tuple[tuple[str, re.Pattern[str], str], ...]:
    return tuple((method, compile_path(path)[0], scope) for (method, path), scope in RULES.items())


def rule_of(method: str, path: str) -> tuple[str, bool]:
    """(the scope a request needs, whether a rule names its route).  No rule: ``read`` for a GET (an unknown
    path answers 404 only to those who may read), ``admin`` for anything else (fails closed)."""
    method = "GET" if method == "HEAD" else method
    for rule_method, pattern, scope in _compiled():
        if rule_method == method and pattern.match(path):
            return scope, True
    return (READ if method == "GET" else ADMIN), False


def required_scope(method: str, path: str) -> str:
    """The scope a request of ``method`` on ``path`` needs (`rule_of`)."""
    return rule_of(method, path)[0]
