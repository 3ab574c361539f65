"""Signing in and out of the web pages, and the admin page (tokens and the audit log).

Pages   GET  /ui/signin?next=PATH       the token field; POST: a right token starts a web session (a random id in
                                        the ``learnest_session`` cookie: HttpOnly, so no script reads it; SameSite
                                        Strict, so no other site's form carries it; Secure over HTTPS) and goes on
                                        to PATH; a wrong one counts toward the failed-token throttle (429 past it)
        POST /ui/signout                ends the session (its row is deleted) and clears the cookie
        GET  /ui/admin                  tokens (name, scope, made by, revoked), a form to make one, revoke
                                        buttons, and the latest entries of the audit log (admin scope)
        POST /ui/admin/tokens           make a token: the answer shows it once (never stored, never cached)
        POST /ui/admin/tokens/{id}/revoke

The cookie holds a session id, never the token: the session's row names the token by its hash, looked up again
on every request (service.api.auth), so revoking the token ends its sessions at once.
"""
from __future__ import annotations

from urllib.parse import urlsplit

from fastapi import APIRouter, Depends, Form, Query, Request
from fastapi.responses import HTMLResponse, RedirectResponse

from ..api.auth import SESSION_COOKIE
from ..api.deps import RowId, actor, get_services
from ..api.throttle import KeyThrottle, client_address
from ..jobs.services import Services
from ..storage import audit, tokens
from . import forms
from .rendering import html_errors, page

router = APIRouter(include_in_schema=False)
AUDIT_SHOWN = 50   # on the admin page (the API and `learnest audit` page through the rest)


def _next(target: str) -> str:
    """Where to go after signing in: a path of this server, never another site (``//evil``, ``https://...``)."""
    parts = urlsplit(target or "/")
    if parts.scheme or parts.netloc or not target.startswith("/") or target.startswith("//") or "\\" in target:
        return "/"
    return target


def _signed_in(request: Request, services: Services) -> tokens.Principal | None:
    """Who the browser's session is (the sign-in routes are public: the guard does not look)."""
    session_id = request.cookies.get(SESSION_COOKIE)
    token_hash = tokens.session_token_hash(services.db, session_id) if session_id else None
    return tokens.principal_of(services.db, token_hash, services.settings.api_key) if token_hash else None


def _protected(services: Services) -> bool:
    return services.settings.api_key is not None or tokens.tokens_exist(services.db)


def _sign_in_form(services: Services, next_path: str, status: int = 200, who: tokens.Principal | None = None,
                  problem: str | None = None) -> HTMLResponse:
    return page("signin.html", "Sign in", status, next=_next(next_path), who=who, protected=_protected(services),
                problem=problem, hours=services.settings.session_hours)


@router.get("/ui/signin", response_class=HTMLResponse)
def sign_in_page(request: Request, next: str = Query("/", max_length=2000),
                 services: Services = Depends(get_services)):
    """The sign-in form (and who the browser is signed in as, if anyone)."""
    return _sign_in_form(services, next, who=_signed_in(request, services))


@router.post("/ui/signin")
def sign_in(request: Request, token: str = Form("", max_length=500), next: str = Form("/", max_length=2000),
            services: Services = Depends(get_services)):
    """Start a web session with a right token; a wrong one is counted as a failed token (429 past the limit)."""
    throttle: KeyThrottle = request.app.state.key_throttle
    address = client_address(request)
    principal = tokens.principal_of(services.db, tokens.hash_token(token.strip()), services.settings.api_key) \
        if token.strip() else None
    if principal is None:
        wait = throttle.retry_after(address)
        if wait is not None:
            refused = _sign_in_form(services, next, 429, problem=throttle.message(wait))
            refused.headers["Retry-After"] = str(wait)
            return refused
        throttle.failed(address)
        return _sign_in_form(services, next, 401, problem="that token is not valid (unknown or revoked)")
    session_id = tokens.start_session(services.db, tokens.hash_token(token.strip()), services.settings.session_hours)
    response = RedirectResponse(_next(next), status_code=303)
    response.set_cookie(SESSION_COOKIE, session_id, max_age=int(services.settings.session_hours * 3600),
                        httponly=True, samesite="strict", secure=request.url.scheme == "https", path="/")
    return response


@router.post("/ui/signout")
def sign_out(request: Request, services: Services = Depends(get_services)):
    """End the browser's session and clear its cookie."""
    session_id = request.cookies.get(SESSION_COOKIE)
    if session_id:
        tokens.end_session(services.db, session_id)
    response = RedirectResponse("/ui/signin", status_code=303)
    response.delete_cookie(SESSION_COOKIE, path="/", httponly=True, samesite="strict")
    return response


@router.get("/ui/admin", response_class=HTMLResponse)
def admin_page(services: Services = Depends(get_services)):
    """Tokens and the latest audit entries."""
    total, entries = audit.list_entries(services.db, AUDIT_SHOWN)
    return page("admin.html", "Tokens and audit log", tokens=tokens.list_tokens(services.db), entries=entries,
                audit_total=total, scopes=tokens.SCOPES, api_key=services.settings.api_key is not None)


@router.post("/ui/admin/tokens")
@html_errors
def create_token_form(request: Request, name: str = Form("", max_length=64), scope: str = Form("read"),
                      services: Services = Depends(get_services)):
    """Make a token and show it, this once (the answer is not cached)."""
    token, row = tokens.create_token(services.db, name.strip(), scope, actor=actor(request))
    response = page("token_created.html", f"Token {row.name}", 201, token=token, row=row)
    response.headers["Cache-Control"] = "no-store"
    return response


@router.post("/ui/admin/tokens/{token_id}/revoke")
@html_errors
def revoke_token_form(request: Request, token_id: RowId, services: Services = Depends(get_services)):
    """Revoke a token, then back to the admin page."""
    tokens.revoke_token(services.db, token_id, actor=actor(request))
    return forms.redirect("/ui/admin")

