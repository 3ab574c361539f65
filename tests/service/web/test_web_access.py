"""Signing in to the web pages, per scope, in Chromium against `learnest serve` (skipped without selenium,
chromium or chromedriver: see test_web_e2e.py) and through the test client: the session cookie is HttpOnly and
SameSite=Strict and holds no token (a script on the page reads nothing), the pages name who is signed in, a read
token cannot post the forms, a write token cannot delete, an admin makes and revokes tokens on the admin page,
a revoked token's session ends at once, and the cross-site rules hold for the sign-in and the forms."""
from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
from test_web_e2e import REPO, SAMPLES, browser, by_css, free_port, wait_for_url, wait_until_up  # noqa: F401
from utils.service import running_app


# -- a server with tokens, and Chromium ----------------------------------------------------------------------
@pytest.fixture(params=["sqlite", "postgresql"])
def served(tmp_path, request):
    """`learnest serve` on a registry (the embedded SQLite, or a throwaway PostgreSQL server) holding an admin, a
    write and a read token (made with `learnest tokens create`, as an administrator would); -> (url, {scope:
    token}, environment)."""
    env = {**os.environ, "LEARNEST_HOME": str(tmp_path / "home"), "LEARNEST_POOL_WORKERS": "1",
           "NO_PROXY": "127.0.0.1,localhost"}
    for name in ("LEARNEST_DATABASE_URL", "LEARNEST_DASK", "LEARNEST_SCHEDULE_SECONDS", "LEARNEST_API_KEY"):
        env.pop(name, None)
    if request.param == "postgresql":
        env["LEARNEST_DATABASE_URL"] = request.getfixturevalue("postgres_url")
    made = {}
    for name, scope in (("ada", "admin"), ("wes", "write"), ("rui", "read")):
        out = subprocess.run([sys.executable, "-m", "learnest.service.cli", "tokens", "create", name, "--scope",
                              scope], env=env, capture_output=True, text=True, check=True)
        made[scope] = out.stdout.strip()
    port, log = free_port(), tmp_path / "server.log"
    with open(log, "wb") as output:
        process = subprocess.Popen([sys.executable, "-m", "learnest.service.cli", "serve", "--port", str(port)],
                                   cwd=REPO, env=env, stdout=output, stderr=subprocess.STDOUT)
    url = f"http://127.0.0.1:{port}"
    try:
        wait_until_up(url, process, log)
        yield url, made, env
    finally:
        process.terminate()
        try:
            process.wait(timeout=30)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()


def sign_in_as(driver, base: str, token: str) -> None:
    driver.get(base + "/")                                  # no session: sent to the sign-in page
    wait_for_url(driver, r"/ui/signin\?next=%2F$")
    form = by_css(driver, "#signin-form")
    form.find_element("name", "token").send_keys(token)
    form.find_element("css selector", "button[type=submit]").click()
    wait_for_url(driver, re.escape(base) + "/$")


def sign_out(driver, base: str) -> None:
    driver.get(base + "/")
    by_css(driver, "#sign-out").click()
    wait_for_url(driver, r"/ui/signin$")


@pytest.mark.browser
def test_each_scope_signs_in_and_is_held_to_it_in_chromium(served, browser):  # noqa: F811
    base, made, env = served
    # read: pages, not forms; the session is invisible to scripts and the token is nowhere in the page
    sign_in_as(browser, base, made["read"])
    assert by_css(browser, "#who").text == "signed in as rui (read)"
    assert browser.execute_script("return document.cookie") == ""
    assert made["read"] not in browser.page_source
    # the form says so (its post would be refused before the file is read: test_access.py)
    assert "does not cover this form" in by_css(browser, "#upload-form").text
    sign_out(browser, base)
    browser.get(base + "/ui/models")
    wait_for_url(browser, r"/ui/signin\?next=%2Fui%2Fmodels$")   # signed out: the session is gone

    # write: uploads, but cannot delete
    sign_in_as(browser, base, made["write"])
    form = by_css(browser, "#upload-form")
    form.find_element("name", "files").send_keys(str(SAMPLES / "circle_rep1.csv"))
    form.find_element("css selector", "button[type=submit]").click()
    wait_for_url(browser, r"/ui/flights/1$")
    browser.get(base + "/ui/flights/1/delete")
    by_css(browser, "form[action='/ui/flights/1/delete'] button[type=submit]").click()
    wait_for_url(browser, r"/ui/flights/1/delete$")
    assert "403" in by_css(browser, "h1").text
    sign_out(browser, base)

    # admin: makes a token on the admin page (shown once), revokes it, deletes the flight; the audit log says who
    sign_in_as(browser, base, made["admin"])
    browser.get(base + "/ui/admin")
    form = by_css(browser, "#token-form")
    form.find_element("name", "name").send_keys("student")
    form.find_element("css selector", "button[type=submit]").click()
    wait_for_url(browser, r"/ui/admin/tokens$")
    student = by_css(browser, "#new-token").text
    assert student.startswith("lnst_") and "student" in by_css(browser, "h1").text
    browser.get(base + "/ui/admin")
    assert student not in browser.page_source
    by_css(browser, "#revoke-4").click()
    wait_for_url(browser, r"/ui/admin$")
    browser.get(base + "/ui/flights/1/delete")
    by_css(browser, "form[action='/ui/flights/1/delete'] button[type=submit]").click()
    wait_for_url(browser, re.escape(base) + "/$")
    browser.get(base + "/ui/admin")
    audit = by_css(browser, "#audit").text
    assert "ada flight.delete flight 1 (circle_rep1)" in audit and "ada token.revoke token student" in audit

    # a revoked token's session ends on its next request (revoked from the command line, another process)
    subprocess.run([sys.executable, "-m", "learnest.service.cli", "tokens", "revoke", "ada"], env=env, check=True,
                   capture_output=True)
    browser.get(base + "/ui/admin")
    wait_for_url(browser, r"/ui/signin\?next=%2Fui%2Fadmin$")


# -- the same rules through the test client -----------------------------------------------------------------
def test_the_session_cookie_and_where_sign_in_leads(tmp_path):
    with running_app(tmp_path / "home", api_key="k3y") as client:
        page = client.get("/ui/signin?next=/ui/models")
        assert page.status_code == 200 and "name='token'" in page.text and "type='password'" in page.text
        wrong = client.post("/ui/signin", data={"token": "nope"})
        assert wrong.status_code == 401 and "not valid" in wrong.text and "learnest_session" not in client.cookies
        for target, lands in (("/ui/models", "/ui/models"), ("https://evil.example/", "/"), ("//evil.example", "/"),
                              ("/\\evil.example", "/")):
            signed = client.post("/ui/signin", data={"token": "k3y", "next": target}, follow_redirects=False)
            assert signed.status_code == 303 and signed.headers["location"] == lands, target
        cookie = signed.headers["set-cookie"].lower()
        assert "httponly" in cookie and "samesite=strict" in cookie and "k3y" not in cookie
        assert "signed in as <b>api-key</b> (admin)" in client.get("/ui/models").text
        # the cookie is for the pages and the forms, never for a JSON write
        assert client.put("/models/m/aliases/a", json={"version": 1}).status_code == 401
        assert client.get("/flights").status_code == 200
        client.post("/ui/signout")
        assert client.get("/flights").status_code == 401


def test_cross_site_posts_are_refused_with_a_session_too(tmp_path):
    with running_app(tmp_path / "home", api_key="k3y") as client:
        client.post("/ui/signin", data={"token": "k3y"})
        evil = {"Origin": "https://evil.example"}
        for url in ("/ui/signin", "/ui/signout", "/ui/flights", "/ui/admin/tokens", "/ui/flights/1/delete"):
            refused = client.post(url, data={"token": "k3y", "name": "x", "scope": "admin"}, headers=evil)
            assert refused.status_code == 403 and "cross-site" in refused.text, url
        assert client.get("/tokens", headers={"X-API-Key": "k3y"}).json() == []


def test_a_revoked_tokens_session_ends_and_the_admin_form_makes_tokens(tmp_path):
    with running_app(tmp_path / "home", api_key="k3y") as client:
        client.post("/ui/signin", data={"token": "k3y"})
        made = client.post("/ui/admin/tokens", data={"name": "sam", "scope": "write"})
        assert made.status_code == 201 and made.headers["cache-control"] == "no-store"
        token = re.search(r"<code id='new-token'>(lnst_[\w-]+)</code>", made.text)[1]
        assert token not in client.get("/ui/admin").text
        client.post("/ui/signout")
        client.post("/ui/signin", data={"token": token})
        assert "signed in as <b>sam</b> (write)" in client.get("/").text
        assert client.get("/ui/admin", follow_redirects=False).status_code == 403
        assert client.post("/tokens/1", headers={"X-API-Key": "k3y"}).status_code == 405
        assert client.delete("/tokens/1", headers={"X-API-Key": "k3y"}).status_code == 200
        gone = client.get("/", headers={"Accept": "text/html"}, follow_redirects=False)
        assert gone.status_code == 303 and gone.headers["location"].startswith("/ui/signin")


def test_an_open_server_shows_no_sign_in_and_says_so(tmp_path):
    with running_app(tmp_path / "home") as client:
        assert client.get("/").status_code == 200 and "signed in as" not in client.get("/").text
        assert "no tokens yet" in client.get("/ui/signin").text


def test_the_key_field_is_gone_from_the_forms(tmp_path: Path):
    with running_app(tmp_path / "home", api_key="k3y", public_reads=True) as client:
        page = client.get("/").text
        assert "name='api_key'" not in page and "Sign in</a> with a token to use this form" in page
        assert "reads are public" in page
