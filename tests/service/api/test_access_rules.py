"""Every route of the app has a scope rule (service.api.access.RULES), and the rule the guard finds for a request
is the one declared for its route: a new route without a rule, a stale rule, or a general path shadowing a
specific one fails here.  The walk covers the OpenAPI schema's operations and the routes left out of it (the
web pages, the docs pages, the mounted static folders)."""
from __future__ import annotations

import re

import pytest

from learnest.service.api.access import ADMIN, PUBLIC, READ, RULES, WRITE, rule_of


def _routes(app) -> set[tuple[str, str]]:
    """(method, path template) of every route the app serves, however FastAPI nests included routers; a mount
    is its folder's GET."""
    from starlette.routing import Mount

    found: set[tuple[str, str]] = set()

    def add(route, path: str) -> None:
        if isinstance(route, Mount):
            found.add(("GET", path.rstrip("/") + "/{path:path}"))
            return
        for method in getattr(route, "methods", None) or ():
            if method != "HEAD":
                found.add((method, path))

    for route in app.routes:
        contexts = getattr(route, "effective_route_contexts", None)
        if contexts is None:
            add(route, route.path)
            continue
        for context in contexts():
            add(context.original_route, context.path)
    return found


@pytest.fixture(scope="module")
def app(tmp_path_factory):
    from learnest.service.app.factory import create_app
    from learnest.service.config import Settings

    return create_app(Settings(home=tmp_path_factory.mktemp("home")))


def test_every_route_has_a_scope_rule_and_every_rule_a_route(app):
    routes = _routes(app)
    assert len(routes) > 60, sorted(routes)            # the walk found the nested routers' routes
    assert sorted(routes - set(RULES)) == []            # a route without a rule
    assert sorted(set(RULES) - routes) == []            # a rule for no route


def test_every_openapi_operation_has_a_scope_rule(app):
    operations = {(method.upper(), path) for path, item in app.openapi()["paths"].items() for method in item}
    assert len(operations) > 30
    assert sorted(operations - set(RULES)) == []


@pytest.mark.parametrize(("method", "path"), sorted(RULES))
def test_the_guard_finds_each_routes_own_rule(method, path):
    concrete = re.sub(r"\{[^}]+\}", "1", path)
    assert rule_of(method, concrete) == (RULES[(method, path)], True)


def test_the_scopes_follow_the_access_model():
    for (method, path), scope in RULES.items():
        if scope == PUBLIC:
            assert path in {"/health", "/ui/signin", "/ui/signout", "/vendor/plotly.min.js"} \
                or path.startswith(("/static/", "/docs-assets/")), path
        elif method == "GET":
            assert scope == (ADMIN if path in ("/tokens", "/audit", "/ui/admin") else READ), path
        elif method == "DELETE" or path.endswith("/delete") or "/tokens" in path:
            assert scope == ADMIN, path
        else:
            assert scope == WRITE, path


def test_a_path_without_a_rule_fails_closed():
    assert rule_of("GET", "/no/such/page") == (READ, False)      # 404 only for those who may read
    assert rule_of("POST", "/no/such/thing") == (ADMIN, False)
    assert rule_of("HEAD", "/flights/3") == (READ, True)
