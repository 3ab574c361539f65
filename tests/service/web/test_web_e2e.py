"""The web pages (service/web/) end to end in a real browser, plus quick checks of escaping and the API key.

The browser test starts `learnest serve` (python -m service.cli serve) on a free loopback port with its own
LEARNEST_HOME and an API key, and drives Debian's headless Chromium through chromedriver with selenium: sign
in with the key, upload two sample logs with the upload form, train a model from the flight page (3 epochs),
wait for the job page, evaluate from the model page, wait, and read the report (per-flight paired dots and
error-over-time plots drawn by plotly.js, per-flight table). A second one evaluates, diagnoses and registers
through the forms only, on two simulated Crazyflie flights with motor PWM and battery and the Crazyflie prior
(trained on both from the flight list's train form), and reads each page's answer off its first line
(LEARNEST_SCREENSHOTS=FOLDER saves the flight, report, diagnosis and model pages as PNGs). Both are skipped,
with the reason, when selenium, /usr/bin/chromium or /usr/bin/chromedriver is missing (CI installs them: see
.ci/run). Selenium is given the driver's path and Selenium Manager is disabled, so nothing is ever downloaded."""
from __future__ import annotations

import os
import re
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import pytest
from utils.service import running_app, wait_for_job

pytestmark = pytest.mark.browser

REPO = Path(__file__).resolve().parents[3]
SAMPLES = REPO / "sample_logs"
CHROMIUM, CHROMEDRIVER = Path("/usr/bin/chromium"), Path("/usr/bin/chromedriver")
API_KEY = "e2e-secret"
CHROMIUM_FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                  "--disable-background-networking", "--disable-component-update", "--disable-sync",
                  "--disable-dev-shm-usage", "--window-size=1280,1000"]


# -- a real server ------------------------------------------------------------------------------------
def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_until_up(url: str, process: subprocess.Popen, log: Path, timeout: float = 90.0) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if process.poll() is not None:
            pytest.fail(f"learnest serve exited with {process.returncode}:\n{log.read_text()[-3000:]}")
        try:
            with urllib.request.urlopen(url + "/health", timeout=2) as answer:
                if answer.status == 200:
                    return
        except OSError:
            time.sleep(0.2)
    pytest.fail(f"learnest serve did not answer within {timeout} s:\n{log.read_text()[-3000:]}")


@pytest.fixture
def server(tmp_path):
    port, log = free_port(), tmp_path / "server.log"
    env = {**os.environ, "LEARNEST_HOME": str(tmp_path / "home"), "LEARNEST_API_KEY": API_KEY,
           "LEARNEST_POOL_WORKERS": "1", "NO_PROXY": "127.0.0.1,localhost"}
    for name in ("LEARNEST_DATABASE_URL", "LEARNEST_DASK", "LEARNEST_SCHEDULE_SECONDS"):
        env.pop(name, None)
    with open(log, "wb") as output:
        process = subprocess.Popen([sys.executable, "-m", "learnest.service.cli", "serve", "--host", "127.0.0.1",
                                    "--port", str(port)], cwd=REPO, env=env, stdout=output, stderr=subprocess.STDOUT)
    url = f"http://127.0.0.1:{port}"
    try:
        wait_until_up(url, process, log)
        yield url
    finally:
        process.terminate()  # uvicorn shuts down cleanly on SIGTERM (and stops its worker process)
        try:
            process.wait(timeout=30)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()
    # a clean stop says nothing more: the pool's workers end by themselves, their semaphores with them
    assert "leaked semaphore" not in log.read_text(), log.read_text()[-2000:]


# -- a headless browser ---------------------------------------------------------------------------------
@pytest.fixture
def browser(tmp_path, monkeypatch):
    webdriver = pytest.importorskip("selenium.webdriver", reason="selenium is not installed (pip install selenium)")
    for path in (CHROMIUM, CHROMEDRIVER):
        if not os.access(path, os.X_OK):
            pytest.skip(f"{path} not found: apt-get install chromium chromium-driver")
    from selenium.webdriver.common.selenium_manager import SeleniumManager

    def no_manager(*_args, **_kwargs):
        raise AssertionError("Selenium Manager must not run (it may download drivers)")
    monkeypatch.setattr(SeleniumManager, "binary_paths", no_manager)

    options = webdriver.ChromeOptions()
    options.binary_location = str(CHROMIUM)
    for flag in CHROMIUM_FLAGS + [f"--user-data-dir={tmp_path / 'chromium-profile'}"]:
        options.add_argument(flag)
    service = webdriver.ChromeService(executable_path=str(CHROMEDRIVER),
                                      log_output=str(tmp_path / "chromedriver.log"))
    driver = webdriver.Chrome(options=options, service=service)
    driver.set_page_load_timeout(60)
    try:
        yield driver
    finally:
        driver.quit()


def by_css(driver, selector: str):
    from selenium.webdriver.common.by import By

    return driver.find_element(By.CSS_SELECTOR, selector)


def image_loaded(driver, selector: str) -> bool:
    return bool(driver.execute_script("const i = document.querySelector(arguments[0]);"
                                      "return i !== null && i.complete && i.naturalWidth > 0;", selector))


def wait_for_url(driver, pattern: str, timeout: float = 60.0) -> None:
    """A click does not wait for the page it leads to: wait for its address and for it to be loaded."""
    from selenium.webdriver.support.ui import WebDriverWait

    WebDriverWait(driver, timeout, poll_frequency=0.1).until(
        lambda d: re.search(pattern, d.current_url)
        and d.execute_script("return document.readyState") == "complete")


def sign_in(driver, base: str, token: str, then: str = "/") -> None:
    """Sign in on /ui/signin (every page needs a token once the server has one) and land on ``then``."""
    from urllib.parse import quote

    driver.get(f"{base}/ui/signin?next={quote(then, safe='')}")
    form = by_css(driver, "#signin-form")
    form.find_element("name", "token").send_keys(token)
    form.find_element("css selector", "button[type=submit]").click()
    wait_for_url(driver, re.escape(base + then) + "$")


def upload_in_browser(driver, base: str, path: Path) -> None:
    driver.get(base + "/")
    form = by_css(driver, "#upload-form")
    form.find_element("name", "files").send_keys(str(path))
    form.find_element("css selector", "button[type=submit]").click()
    wait_for_url(driver, r"/ui/flights/\d+$")


def wait_for_job_page(driver, timeout: float = 120.0) -> str:
    """The job page reloads itself (meta refresh) until the job is done; -> its final state."""
    from selenium.common.exceptions import WebDriverException
    from selenium.webdriver.support.ui import WebDriverWait

    def finished(d):
        state = by_css(d, "#job-state").text
        return state if state in ("succeeded", "failed") else False
    # a query that lands while the page reloads itself can fail in Chromium's inspector ("unhandled inspector
    # error", seen at load 8): poll again; a page that never shows a final state still times out
    return WebDriverWait(driver, timeout, poll_frequency=0.3, ignored_exceptions=(WebDriverException,)).until(finished)


def test_upload_train_evaluate_and_report_in_chromium(server, browser):
    sign_in(browser, server, API_KEY)   # LEARNEST_API_KEY is an admin token
    # upload two flights through the form
    upload_in_browser(browser, server, SAMPLES / "circle_rep1.csv")
    assert "circle_rep1" in by_css(browser, "h1").text and image_loaded(browser, "#trajectory")
    assert "ok" in by_css(browser, "#flight-facts").text
    first_flight = browser.current_url
    upload_in_browser(browser, server, SAMPLES / "circle_rep2.csv")
    assert "circle_rep2" in by_css(browser, "h1").text
    browser.get(server + "/")
    listing = by_css(browser, "#flights").text
    assert "circle_rep1" in listing and "circle_rep2" in listing

    # train from the first flight's page, follow the job page until it is done
    browser.get(first_flight)
    form = by_css(browser, "#train-form")
    form.find_element("name", "name").send_keys("e2e")
    form.find_element("name", "epochs").send_keys("3")
    form.find_element("css selector", "button[type=submit]").click()
    wait_for_url(browser, r"/ui/jobs/\d+$")
    assert wait_for_job_page(browser) == "succeeded"
    browser.find_element("link text", "model e2e").click()
    wait_for_url(browser, r"/ui/models/e2e$")
    assert by_css(browser, "h1").text == "Model e2e" and image_loaded(browser, "#loss-curve")
    assert "ready" in by_css(browser, "#versions").text

    # evaluate every other flight with the UKFs only (the MHEs are covered by the service tests)
    form = by_css(browser, "#evaluate-form")
    for method in ("mhe", "knode-mhe"):
        form.find_element("css selector", f"input[name=methods][value={method}]").click()
    form.find_element("css selector", "button[type=submit]").click()
    wait_for_url(browser, r"/ui/jobs/\d+$")
    assert wait_for_job_page(browser) == "succeeded"
    by_css(browser, "#report-link").click()
    wait_for_url(browser, r"/evaluations/\d+/report\.html")

    # the report (on the site's template: its nav and stylesheet): per-flight paired dots and the error-over-time
    # plots drawn by plotly.js (served by the app, no CDN) from the stored estimates, and the per-flight table
    assert "Evaluation" in by_css(browser, "h1").text and "models" in by_css(browser, "nav").text
    assert browser.execute_script("return getComputedStyle(document.querySelector('nav')).borderBottomStyle") == "solid"
    from selenium.webdriver.support.ui import WebDriverWait
    for plot in ("#paired-plot", "#error-plot"):
        WebDriverWait(browser, 30).until(
            lambda driver, plot=plot: driver.execute_script(
                f"return document.querySelectorAll('{plot} svg.main-svg').length") > 0)
    table = by_css(browser, "table").text
    assert "circle_rep2" in table and "knode-ukf" in table and "median" in table
    assert "circle_rep2" in by_css(browser, "select[name=flight]").text


# -- quick checks without a browser ---------------------------------------------------------------------
def post_upload(client, name: str, data: dict | None = None, **kwargs):
    files = [("files", (name, (SAMPLES / "circle_rep1.csv").read_bytes()))]
    return client.post("/ui/flights", files=files, data=data or {}, follow_redirects=False, **kwargs)


def test_every_page_extends_the_base_template_and_links_the_one_stylesheet(tmp_path):
    with running_app(tmp_path / "home") as client:
        assert post_upload(client, "a.csv").status_code == 303
        css = client.get("/static/style.css")
        assert css.status_code == 200 and css.headers["content-type"].startswith("text/css") and "nav" in css.text
        for url in ("/", "/ui/flights/1", "/ui/models", "/ui/jobs", "/ui/flights/42"):
            page = client.get(url).text
            assert page.count("<link rel='stylesheet' href='/static/style.css'>") == 1, url
            assert "<style" not in page and page.count("<nav>") == 1, url


def test_user_text_is_escaped_everywhere(tmp_path):
    hostile = "<script>alert(1)</script>"
    with running_app(tmp_path / "home") as client:
        answer = post_upload(client, "<img src=x onerror=alert(2)>.csv", {"vehicle": hostile, "notes": hostile})
        assert answer.status_code == 303
        page = client.get(answer.headers["location"]).text
        assert "<script>alert" not in page and "<img src=x" not in page
        assert "&lt;script&gt;alert(1)&lt;/script&gt;" in page and "&lt;img src=x onerror=alert(2)&gt;.csv" in page
        listing = client.get("/").text
        assert "<script>alert" not in listing and "&lt;script&gt;" in listing
        bad = client.post("/ui/models", data={"name": "<b>x</b>", "flight_id": "1"})
        assert bad.status_code == 422 and "<b>x</b>" not in bad.text and "name:" in bad.text


def test_pages_and_form_writes_need_a_signed_in_session(tmp_path):
    with running_app(tmp_path / "home", api_key="s3cret") as client:
        away = client.get("/", headers={"Accept": "text/html"}, follow_redirects=False)
        assert away.status_code == 303 and away.headers["location"] == "/ui/signin?next=%2F"
        for key in (None, "wrong"):
            refused = post_upload(client, "a.csv", {"api_key": key} if key else {})
            assert refused.status_code == 401 and "sign in" in refused.text
        signed = client.post("/ui/signin", data={"token": "s3cret", "next": "/"}, follow_redirects=False)
        assert signed.status_code == 303 and signed.headers["location"] == "/"
        cookie = signed.headers["set-cookie"].lower()
        assert "learnest_session=" in cookie and "httponly" in cookie and "samesite=strict" in cookie
        assert "s3cret" not in cookie                     # the cookie holds a session id, never the token
        accepted = post_upload(client, "a.csv", {})
        assert accepted.status_code == 303
        assert "name='api_key'" not in client.get("/").text
        assert "name='group_by'" in client.get("/").text   # the train form's grouping, refused when unread
        bad_group = client.post("/ui/models", data={"name": "q", "flight_id": "1", "epochs": "1", "group_by": "name:("})
        assert bad_group.status_code == 422 and "does not compile" in bad_group.text
        train = client.post("/ui/models", data={"name": "q", "flight_id": "1", "epochs": "1"}, follow_redirects=False)
        assert train.status_code == 303 and train.headers["location"].startswith("/ui/jobs/")
        job_id = int(train.headers["location"].rsplit("/", 1)[1])
        assert wait_for_job(client, job_id)["state"] == "succeeded"
        assert client.post("/ui/signout", follow_redirects=False).status_code == 303
        client.cookies.clear()
        assert client.post("/ui/models/q/aliases", data={"alias": "production", "version": "1"}).status_code == 401
        # the JSON API takes the header
        assert client.put("/models/q/aliases/production", json={"version": 1},
                          headers={"X-API-Key": "s3cret"}).status_code == 200


def test_missing_things_and_bad_forms_are_html_error_pages(tmp_path):
    with running_app(tmp_path / "home") as client:
        for url in ("/ui/flights/42", "/ui/models/nobody", "/ui/jobs/42"):
            answer = client.get(url)
            assert answer.status_code == 404 and answer.headers["content-type"].startswith("text/html")
        junk = client.post("/ui/flights", files=[("files", ("junk.bin", b"\x00\x01" * 100))])
        assert junk.status_code == 422 and "junk.bin" in junk.text and "text/html" in junk.headers["content-type"]
        nothing = client.post("/ui/flights", files=[("files", ("", b""))])
        assert nothing.status_code == 422 and "choose the log file" in nothing.text
        unknown = client.post("/ui/evaluations", data={"model": "nobody", "methods": ["ukf"]})
        assert unknown.status_code == 404 and "nobody" in unknown.text


SCREENS = Path(os.environ.get("LEARNEST_SCREENSHOTS", "")) if os.environ.get("LEARNEST_SCREENSHOTS") else None


def screenshot(driver, name: str) -> None:
    """With LEARNEST_SCREENSHOTS=FOLDER, save the whole page as FOLDER/NAME.png (for people to look at)."""
    if SCREENS is None:
        return
    SCREENS.mkdir(parents=True, exist_ok=True)
    height = driver.execute_script("return document.documentElement.scrollHeight")
    driver.set_window_size(1280, min(max(1000, height), 6000))
    driver.save_screenshot(str(SCREENS / f"{name}.png"))
    driver.set_window_size(1280, 1000)


def submit(form) -> None:
    form.find_element("css selector", "button[type=submit]").click()


def upload_flight_file(driver, base: str, path: Path) -> None:
    driver.get(base + "/")
    form = by_css(driver, "#upload-form")
    form.find_element("name", "files").send_keys(str(path))
    submit(form)
    wait_for_url(driver, r"/ui/flights/\d+$")


def crazyflie_logs(folder: Path) -> list[Path]:
    """Two 20-s Crazyflie flights flown by `learnest.models.crazyflie.simulate_crazyflie` whose battery exponent
    (gamma 1.2) the prior gets wrong, written as NanoBench CSVs with motor PWM and battery voltage: the
    Crazyflie prior applies, and the diagnosis has a known effect to find and a repair that helps."""
    from learnest.ingest.formats.nanobench import writer as nanobench
    from learnest.models import crazyflie as cf
    from learnest.models.crazyflie.simulate_crazyflie import SimulatedFlight, simulate_crazyflie

    paths = []
    for seed in (0, 1):
        f = simulate_crazyflie(SimulatedFlight(truth={**cf.IDENTIFIED, "gamma": 1.2}, duration_s=20), seed=seed)
        paths.append(folder / f"cf_battery{seed}.csv")
        nanobench.write(paths[-1], f.t + 1.7e9, f.p, f.quat, f.channels["acc_body"] / cf.GRAVITY,
                        motors=f.channels["motors"], vbat=f.channels["vbat"])
    return paths


HEADLINE = (r"KNODE-UKF carried the estimate through mocap gaps \d+\.\d % (better|worse) than its prior UKF "
            r"\(median of 1 flight; (95 % interval \[[-+]\d+\.\d, [-+]\d+\.\d\] %|one flight, no interval)\): "
            r"better on [01] of 1; of 1 flight scored, worse beyond its 95 % interval on (none|1), better beyond "
            r"it on (none|1), within it on (none|1), undecided \(no interval\) on (none|1)\.")


def test_evaluate_diagnose_and_register_through_the_forms_reading_each_answer(server, browser, tmp_path):
    """Everything through the forms on two Crazyflie flights with motor PWM and battery (the Crazyflie prior):
    upload, train one model on both from the flight list's train form (one trains, the other is held out
    whole), then evaluate and diagnose (asking to register the repaired model) from the model page; each page's
    first line is its answer, the diagnosis names the effect the simulation put in, and says why the repair,
    judged like with like, is not registered."""
    from selenium.webdriver.support.ui import Select, WebDriverWait

    logs = crazyflie_logs(tmp_path)
    sign_in(browser, server, API_KEY)
    names = [path.stem for path in logs]
    for path in logs:
        upload_flight_file(browser, server, path)
        assert path.stem in by_css(browser, "h1").text and "ok" in by_css(browser, "#flight-facts").text
    screenshot(browser, "flight")

    # train on both flights from the flight list: the checkboxes, the prior and the epochs
    browser.get(server + "/")
    for flight_id in ("1", "2"):
        by_css(browser, f"input[name=flight_ids][value='{flight_id}']").click()
    form = by_css(browser, "#train-form")
    form.find_element("name", "name").send_keys("forms")
    Select(form.find_element("name", "system")).select_by_value("crazyflie")
    form.find_element("name", "epochs").send_keys("3")
    submit(form)
    wait_for_url(browser, r"/ui/jobs/\d+$")
    assert wait_for_job_page(browser, timeout=300) == "succeeded", by_css(browser, "body").text
    browser.find_element("link text", "model forms").click()
    wait_for_url(browser, r"/ui/models/forms$")
    assert by_css(browser, "#headline-sentence").text.startswith("Not evaluated yet")
    versions = by_css(browser, "#versions").text
    assert "crazyflie" in versions
    # one of the two trains, the other is held out whole to choose the kept epoch; the evaluation scores it
    trained, = [name for name in names if name in versions]
    held_out, = set(names) - {trained}
    browser.get(server + "/ui/models/forms/versions/1")
    assert held_out in by_css(browser, "body").text

    # evaluate from the model page on every flight but the one it trained on (UKFs only: quick)
    browser.get(server + "/ui/models/forms")
    form = by_css(browser, "#evaluate-form")
    for method in ("mhe", "knode-mhe"):
        form.find_element("css selector", f"input[name=methods][value={method}]").click()
    submit(form)
    wait_for_url(browser, r"/ui/jobs/\d+$")
    assert wait_for_job_page(browser, timeout=300) == "succeeded", by_css(browser, "body").text
    on_job_page = by_css(browser, "#headline-sentence").text
    by_css(browser, "#report-link").click()
    wait_for_url(browser, r"/evaluations/\d+/report\.html")
    sentence = by_css(browser, "#headline-sentence").text
    assert sentence == on_job_page
    assert re.match(HEADLINE, sentence), sentence
    assert image_loaded(browser, "#gain-figure")
    # the answer comes first: above the per-flight table, which is above the folded details
    top = {k: browser.execute_script(f"return document.querySelector('{k}').getBoundingClientRect().top")
           for k in ("#headline-sentence", "#mse", "#details-settings")}
    assert top["#headline-sentence"] < top["#mse"] < top["#details-settings"]
    WebDriverWait(browser, 30).until(lambda d: d.execute_script(
        "return document.querySelectorAll('#difference-plot svg.main-svg').length") > 0)
    screenshot(browser, "report")
    # the export form downloads one flight's estimates through the API's own route
    export = by_css(browser, "#export-form")
    assert export.get_attribute("action").endswith("/estimates") and held_out in export.text

    # diagnose from the model page with the Crazyflie prior: two flights in order (the first fits, the second
    # is scored), asking to register the repaired model as the next version
    browser.get(server + "/ui/models/forms")
    form = by_css(browser, "#diagnose-form")
    assert Select(form.find_element("name", "system")).first_selected_option.get_attribute("value") == "crazyflie"
    for flight_id in ("1", "2"):
        form.find_element("css selector", f"input[name=flights][value='{flight_id}']").click()
    form.find_element("name", "epochs").send_keys("3")
    form.find_element("name", "register").click()
    submit(form)
    wait_for_url(browser, r"/ui/jobs/\d+$")
    assert wait_for_job_page(browser, timeout=600) == "succeeded", by_css(browser, "body").text
    job_page = by_css(browser, "body").text
    # the model runs with its identified noise, and so does the repair: on the one held-out flight the repair's
    # gain lies within that flight's interval, so nothing is registered, and the report says why
    assert "registered version" not in job_page, job_page
    on_job_page = by_css(browser, "#headline-sentence").text
    by_css(browser, "#diagnosis-link").click()
    wait_for_url(browser, r"/diagnoses/\d+/report\.html")
    assert by_css(browser, "#headline-sentence").text.startswith("Found battery_thrust")   # the simulated effect
    assert by_css(browser, "#headline-sentence").text == on_job_page
    assert by_css(browser, "#registered").text.startswith("nothing registered: the repair does not improve")
    assert by_css(browser, "#diagnosis-split").text.startswith(f"Split: fitted on {names[0]}; scored on {names[1]} (")
    assert image_loaded(browser, "#diagnosis-summary")
    screenshot(browser, "diagnosis")

    # the model page keeps its one version, under the newest evaluation's answer
    browser.get(server + "/ui/models/forms")
    assert by_css(browser, "#headline-sentence").text == sentence
    versions = by_css(browser, "#versions").text
    assert "ready" in versions and versions.count("ready") == 1 and versions.count("crazyflie") == 1
    screenshot(browser, "model")
