"""Service hardening (issue 10).  Item 5: with no API key (the default), a page on another site must not be
able to start jobs through the user's browser (CSRF), and a server on localhost must not answer requests for
other host names (DNS rebinding).  The real app, the real forms; the attack is what a browser would send.
Item 10: numbers and dates out of range are a 422, not a 500."""
import pytest
from utils.service import flight_csv, running_app, upload


@pytest.fixture(scope="module")
def app_with_a_flight(tmp_path_factory):
    home = tmp_path_factory.mktemp("guard")
    with running_app(home) as client:
        response = upload(client, flight_csv(home / "logs" / "f.csv", seed=1))
        assert response.status_code == 201, response.text
        yield client, response.json()["id"]


def _jobs(client) -> int:
    return len(client.get("/jobs").json()["items"])


@pytest.mark.parametrize("headers", [
    {"Origin": "http://evil.example"},
    {"Origin": "null"},                                   # sandboxed frames and data: URLs send this
    {"Origin": "http://testserver.evil.example"},         # a look-alike name is another site
    {"Sec-Fetch-Site": "cross-site"},
    {"Referer": "http://evil.example/attack.html"},
])
def test_a_cross_site_form_post_starts_no_job(app_with_a_flight, headers):
    client, flight_id = app_with_a_flight
    before = _jobs(client)
    response = client.post("/ui/models", data={"name": "pwned", "flight_id": str(flight_id), "epochs": "1"},
                           headers=headers, follow_redirects=False)
    assert response.status_code == 403
    assert "cross-site request refused" in response.json()["detail"]
    assert _jobs(client) == before
    # the JSON routes are guarded the same way (a browser can POST there too)
    assert client.post("/models", json={"name": "pwned", "flight_id": flight_id}, headers=headers).status_code == 403


def test_a_same_site_form_post_and_a_plain_client_still_work(app_with_a_flight):
    client, flight_id = app_with_a_flight
    before = _jobs(client)
    form = {"name": "ok", "flight_id": str(flight_id), "epochs": "1"}
    same_site = client.post("/ui/models", data=form, headers={"Origin": "http://testserver",
                                                              "Sec-Fetch-Site": "same-origin"},
                            follow_redirects=False)
    assert same_site.status_code == 303, same_site.text
    plain = client.post("/ui/models", data=form, follow_redirects=False)   # curl: no Origin, no Referer
    assert plain.status_code == 303, plain.text
    assert _jobs(client) == before + 2


@pytest.mark.parametrize("host", ["evil.example", "evil.example:8000", "127.0.0.1.nip.io"])
def test_a_request_for_another_host_name_is_refused(app_with_a_flight, host):
    client, _ = app_with_a_flight
    response = client.get("/flights", headers={"Host": host})
    assert response.status_code == 400
    assert "is not served here" in response.json()["detail"] and "LEARNEST_ALLOWED_HOSTS" in response.json()["detail"]


def test_the_served_names_answer(app_with_a_flight):
    client, _ = app_with_a_flight
    for host in ("localhost:8000", "127.0.0.1", "[::1]:8000", "testserver"):
        assert client.get("/flights", headers={"Host": host}).status_code == 200, host


@pytest.mark.parametrize("header, name", [("localhost:8000", "localhost"), ("[::1]:8000", "::1"), ("::1", "::1"),
                                          ("Example.ORG", "example.org"), ("10.0.0.5:80", "10.0.0.5")])
def test_host_name_strips_the_port(header, name):
    from learnest.service.api.request_guard import host_name

    assert host_name(header) == name


# -- issue 10, item 10: out-of-range ids and dates are a 422 that says so, never a 500 -------------------
@pytest.mark.parametrize("path", ["/flights/9223372036854775808", "/jobs/99999999999999999999",
                                  "/flights?offset=9223372036854775808", "/jobs?offset=18446744073709551616",
                                  "/models/quad/versions/9223372036854775808", "/evaluations/9223372036854775808",
                                  "/ui/flights/9223372036854775808", "/?offset=9223372036854775808",
                                  "/flights?since=0001-01-01T00:00:00%2B14:00",
                                  "/flights?until=9999-12-31T23:00:00-05:00"])
def test_out_of_range_numbers_are_a_422_not_a_500(app_with_a_flight, path):
    client, _ = app_with_a_flight
    response = client.get(path)
    assert response.status_code == 422, (path, response.status_code, response.text[:300])
    # the largest id that can exist is a plain 404
    assert client.get("/flights/9223372036854775807").status_code == 404
