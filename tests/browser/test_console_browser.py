"""The operator console in a real browser: Debian's headless ``chromium`` driven by Selenium through
``chromium-driver``, against a daemon on the simulated cell (the real runner, the shipped ``default-band`` plan,
coarse scans) served by uvicorn on 127.0.0.1 from a thread (docs/console.md).

The run writes console-cell.png, console-running-job.png and console-3d-view.png into the folder named by
``TANDEMSCAN_SCREENSHOTS`` (``TANDEMSCAN_SCREENSHOTS=docs make test`` refreshes docs/'s pictures), else into a
temporary folder, so a test run leaves the work tree as it was.
"""

from __future__ import annotations

import asyncio
import io
import json
import os
import shutil
import socket
import tempfile
import threading
import time
from pathlib import Path

import httpx
import numpy as np
import pytest
from serving import running_server
from tandemscan.config import load_config
from tandemscan.daemon.api.app import create_app
from tandemscan.daemon.service import Daemon
from tandemscan.drivers.errors import DeviceError
from tandemscan.sim_drivers.cell import Simulation, with_surveyed_mounts

webdriver = pytest.importorskip("selenium.webdriver", reason="selenium not installed (pip install -e '.[dev]')")
from PIL import Image  # noqa: E402 - after the skip: selenium is what the module needs first
from selenium.common.exceptions import StaleElementReferenceException  # noqa: E402
from selenium.webdriver.common.action_chains import ActionChains  # noqa: E402
from selenium.webdriver.common.by import By  # noqa: E402
from selenium.webdriver.support.ui import WebDriverWait  # noqa: E402

CHROMIUM = shutil.which("chromium")
CHROMEDRIVER = shutil.which("chromedriver")
pytestmark = pytest.mark.skipif(CHROMIUM is None or CHROMEDRIVER is None,
                                reason="Debian's chromium and chromium-driver are not installed (make system-deps)")

TOKEN = "console-token"
SCREENSHOTS = Path(os.environ.get("TANDEMSCAN_SCREENSHOTS") or tempfile.mkdtemp(prefix="console-screenshots-"))
BACKGROUND_RGB = np.array([16, 21, 28])  # the 3D view's clear colour (view3d.js)


class CellDaemon:
    """A daemon on the simulated cell in a thread with its own event loop; ``call`` runs a coroutine there."""

    def __init__(self, state: Path):
        config = load_config()
        # motion takes a little wall time, so that an operator stop lands while a step is under way
        config = config.model_copy(update={"sim": config.sim.model_copy(update={"time_scale": 0.05})})
        config = with_surveyed_mounts(config, Simulation(config), state.parent)  # the part's verdict: pass
        self.daemon: Daemon | None = None
        self.url = ""
        self._state, self._config = state, config
        self._started, self._stop = threading.Event(), threading.Event()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread = threading.Thread(target=lambda: asyncio.run(self._serve()), daemon=True)

    async def _serve(self) -> None:
        self._loop = asyncio.get_running_loop()
        self.daemon = Daemon(self._config, self._state, token=TOKEN)
        async with running_server(create_app(self.daemon, manage_lifecycle=True)) as url:
            self.url = url
            self._started.set()
            while not self._stop.is_set():
                await asyncio.sleep(0.05)

    def __enter__(self) -> CellDaemon:
        self._thread.start()
        assert self._started.wait(120), "daemon did not start"
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join(60)

    def call(self, coro):
        return asyncio.run_coroutine_threadsafe(coro, self._loop).result(30)

    def get(self, path: str) -> dict:
        return httpx.get(self.url + path, headers={"Authorization": f"Bearer {TOKEN}"}, timeout=10).json()


class DroppingProxy:
    """A TCP relay in front of the daemon whose :meth:`drop` cuts every open connection (a dropped link)."""

    def __init__(self, upstream_port: int):
        self.upstream_port = upstream_port
        self.listener = socket.create_server(("127.0.0.1", 0))
        self.port = self.listener.getsockname()[1]
        self.open: set[socket.socket] = set()
        self.lock = threading.Lock()
        threading.Thread(target=self._accept, daemon=True).start()

    def _accept(self) -> None:
        while True:
            try:
                client, _ = self.listener.accept()
            except OSError:
                return
            upstream = socket.create_connection(("127.0.0.1", self.upstream_port))
            with self.lock:
                self.open |= {client, upstream}
            for a, b in ((client, upstream), (upstream, client)):
                threading.Thread(target=self._pipe, args=(a, b), daemon=True).start()

    def _pipe(self, src: socket.socket, dst: socket.socket) -> None:
        try:
            while data := src.recv(65536):
                dst.sendall(data)
        except OSError:
            pass
        for s in (src, dst):
            self._close(s)

    def _close(self, s: socket.socket) -> None:
        with self.lock:
            self.open.discard(s)
        try:
            s.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass
        s.close()

    def drop(self) -> None:
        with self.lock:
            sockets = list(self.open)
        for s in sockets:
            self._close(s)

    def close(self) -> None:
        self.listener.close()
        self.drop()


@pytest.fixture(scope="module")
def cell(tmp_path_factory):
    with CellDaemon(tmp_path_factory.mktemp("console") / "state") as d:
        proxy = DroppingProxy(int(d.url.rsplit(":", 1)[1]))
        d.browser_url, d.proxy = f"http://127.0.0.1:{proxy.port}", proxy
        yield d
        proxy.close()


@pytest.fixture(scope="module")
def browser():
    from selenium.webdriver.chrome.options import Options
    from selenium.webdriver.chrome.service import Service

    options = Options()
    options.binary_location = CHROMIUM
    options.set_capability("goog:loggingPrefs", {"performance": "ALL"})  # requests, to see Last-Event-ID
    for arg in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage", "--use-angle=swiftshader",
                "--enable-unsafe-swiftshader", "--window-size=1280,800", "--hide-scrollbars"):
        options.add_argument(arg)
    driver = webdriver.Chrome(service=Service(CHROMEDRIVER), options=options)
    driver.set_page_load_timeout(30)
    metrics(driver, 1280, 800)
    yield driver
    driver.quit()


def metrics(driver, width: int, height: int, mobile: bool = False) -> None:
    """Emulate a viewport of ``width`` x ``height`` CSS px (a touch tablet with ``mobile``)."""
    driver.execute_cdp_cmd("Emulation.setDeviceMetricsOverride",
                           {"width": width, "height": height, "deviceScaleFactor": 1, "mobile": mobile})
    driver.execute_cdp_cmd("Emulation.setTouchEmulationEnabled", {"enabled": mobile})


def wait(driver, what, timeout_s: float = 60.0, message: str = ""):
    # tables are rebuilt each second: an element found a moment ago may be gone, so look again
    return WebDriverWait(driver, timeout_s, poll_frequency=0.1, ignored_exceptions=(StaleElementReferenceException,)) \
        .until(lambda d: what(d), message)


def device_row(driver, name: str) -> dict | None:
    """The devices panel's row of ``name`` as the page shows it now: link, state, detail, class."""
    return driver.execute_script("""
        const tr = document.querySelector(`#devices tr[data-device="${arguments[0]}"]`);
        return tr && {link: tr.children[1].innerText, state: tr.children[2].innerText,
                      detail: tr.children[3].innerText, cls: tr.className};""", name)


def text(driver, element_id: str) -> str:
    return driver.find_element(By.ID, element_id).text


def visible(driver, element_id: str) -> bool:
    return driver.find_element(By.ID, element_id).is_displayed()


def click(driver, element_id: str) -> None:
    el = driver.find_element(By.ID, element_id)
    driver.execute_script("arguments[0].scrollIntoView({block: 'center'})", el)
    el.click()


def sign_in(driver, url: str, token: str = TOKEN) -> None:
    driver.get(url + "/")
    wait(driver, lambda d: visible(d, "signin") or visible(d, "app"))
    if visible(driver, "app"):
        return
    field = driver.find_element(By.ID, "token-input")
    field.clear()
    field.send_keys(token)
    click(driver, "signin-button")


def canvas_pixels(driver) -> np.ndarray:
    """The 3D view's canvas as the browser composited it (RGB, uint8)."""
    canvas = driver.find_element(By.ID, "cloud-canvas")
    driver.execute_script("arguments[0].scrollIntoView({block: 'center'})", canvas)
    png = canvas.screenshot_as_png
    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB")).astype(int)


def test_sign_in_keeps_the_token_for_the_tab_and_401_returns_to_it(cell, browser):
    sign_in(browser, cell.browser_url, "wrong-token")
    wait(browser, lambda d: "not accepted" in text(d, "signin-error"))
    assert not visible(browser, "app")
    sign_in(browser, cell.browser_url)
    wait(browser, lambda d: visible(d, "app"))
    assert browser.execute_script("return sessionStorage.getItem('tandemscan.token')") == TOKEN
    assert browser.execute_script("return localStorage.length") == 0
    browser.refresh()  # the same tab keeps it
    wait(browser, lambda d: visible(d, "app"))
    # a token the daemon no longer accepts: the next call's 401 goes back to sign-in
    browser.execute_script("sessionStorage.setItem('tandemscan.token', 'revoked')")
    wait(browser, lambda d: visible(d, "signin"), 10)
    assert "401" in text(browser, "signin-error")
    sign_in(browser, cell.browser_url)
    wait(browser, lambda d: visible(d, "app"))


def test_devices_panel_follows_an_injected_device_fault(cell, browser):
    sign_in(browser, cell.browser_url)
    wait(browser, lambda d: len(d.find_elements(By.CSS_SELECTOR, "#devices tbody tr")) == 6)
    wait(browser, lambda d: device_row(d, "tracker")["link"] == "connected")
    browser.save_screenshot(str(SCREENSHOTS / "console-cell.png"))
    tracker = cell.daemon.cell.tracker
    reconnect = tracker.connect

    async def link_down() -> None:
        raise DeviceError("tracker", "injected fault: no answer on the link")

    tracker.connect = link_down  # reconnects fail until the fault is cleared
    cell.call(tracker.close())
    try:
        wait(browser, lambda d: "injected fault" in device_row(d, "tracker")["detail"], 20)
        row = device_row(browser, "tracker")
        assert row["link"] == "disconnected" and "device-fault" in row["cls"]
        assert device_row(browser, "scanner")["link"] == "connected"
    finally:
        tracker.connect = reconnect
    wait(browser, lambda d: device_row(d, "tracker")["link"] == "connected", 40)
    assert "device-fault" not in device_row(browser, "tracker")["cls"]


def event_stream_requests(driver) -> list[dict]:
    """Headers of the requests for /v1/events the page made since the last call (performance log)."""
    found = []
    for entry in driver.get_log("performance"):
        msg = json.loads(entry["message"])["message"]
        if msg["method"] == "Network.requestWillBeSent" and "/v1/events" in msg["params"]["request"]["url"]:
            found.append(msg["params"]["request"]["headers"])
    return found


def test_job_is_stopped_reset_resumed_and_followed_to_100_percent(cell, browser):
    sign_in(browser, cell.browser_url)
    wait(browser, lambda d: d.find_elements(By.CSS_SELECTOR, "#plan-select option[value='default-band']"))
    browser.find_element(By.ID, "label-input").send_keys("order 17")
    click(browser, "submit-button")
    wait(browser, lambda d: text(d, "job-state") == "running")
    job_id = text(browser, "job-id")
    assert "order 17" in text(browser, "job-label")
    wait(browser, lambda d: float(d.find_element(By.ID, "job-progress").get_attribute("value")) > 0, 60)
    wait(browser, lambda d: d.find_elements(By.CSS_SELECTOR, "#plan-svg polygon[data-robot]"))
    assert len(browser.find_elements(By.CSS_SELECTOR, "#plan-svg rect")) == 3  # the measurement AGV's stations
    assert len(browser.find_elements(By.CSS_SELECTOR, "#plan-svg circle")) == 2  # the tracking AGV's
    assert " of 39" in text(browser, "job-step")
    browser.save_screenshot(str(SCREENSHOTS / "console-running-job.png"))

    # a dropped connection: the console reconnects and resumes from the last event it saw
    wait(browser, lambda d: text(d, "stream-status") == "event stream: live")
    event_stream_requests(browser)
    cell.proxy.drop()
    last_seq = cell.daemon.store.last_event_seq()
    wait(browser, lambda d: "reconnecting" in text(d, "stream-status"), 10)
    wait(browser, lambda d: text(d, "stream-status") == "event stream: live", 20)
    resumed = [h.get("Last-Event-ID") for h in event_stream_requests(browser)]
    assert resumed and resumed[-1] is not None and 0 < int(resumed[-1]) <= last_seq

    assert browser.find_element(By.ID, "stop-button").is_enabled()
    click(browser, "stop-button")
    wait(browser, lambda d: visible(d, "latch-banner"), 10)
    assert "operator stop" in text(browser, "latch-banner")
    wait(browser, lambda d: text(d, "job-state") == "paused_safety", 20)
    assert cell.get(f"/v1/jobs/{job_id}")["state"] == "paused_safety"
    progress_at_stop = float(browser.find_element(By.ID, "job-progress").get_attribute("value"))
    assert progress_at_stop < 100
    assert browser.find_element(By.ID, "stop-button").is_enabled()  # stop stays available while latched

    wait(browser, lambda d: d.find_element(By.ID, "reset-button").is_enabled(), 10)
    click(browser, "reset-button")
    wait(browser, lambda d: not visible(d, "latch-banner"), 10)
    assert cell.get("/v1/devices")["safety"]["latched"] is False
    wait(browser, lambda d: d.find_element(By.ID, "resume-button").is_enabled(), 10)
    click(browser, "resume-button")
    wait(browser, lambda d: text(d, "job-state") == "running", 10)
    wait(browser, lambda d: text(d, "job-progress-text") == "100 %", 150)
    wait(browser, lambda d: text(d, "job-state") == "succeeded", 60)
    assert float(browser.find_element(By.ID, "job-progress").get_attribute("value")) == 100
    wait(browser, lambda d: d.find_elements(By.CSS_SELECTOR, f"#history tr[data-job='{job_id}']"), 15)


def _finished_job(cell) -> str:
    done = cell.get("/v1/jobs?state=succeeded&limit=1")["items"]
    if done:
        return done[0]["id"]
    job = httpx.post(cell.url + "/v1/jobs", json={}, headers={"Authorization": f"Bearer {TOKEN}"}).json()
    for _ in range(1200):
        if cell.get(f"/v1/jobs/{job['id']}")["state"] == "succeeded":
            return job["id"]
        time.sleep(0.1)
    raise AssertionError("the job did not succeed")


def test_finished_job_shows_verdict_links_and_a_3d_view_that_draws(cell, browser):
    job_id = _finished_job(cell)
    sign_in(browser, cell.browser_url)
    button = f"#history button[data-job='{job_id}']"
    wait(browser, lambda d: d.find_elements(By.CSS_SELECTOR, button), 20)
    browser.execute_script("document.querySelector(arguments[0]).click()", button)  # the row may be rebuilt
    wait(browser, lambda d: d.find_element(By.ID, "cloud-canvas").get_attribute("data-points"), 60)
    verdict = text(browser, "verdict")  # the default part is its own CAD: no deviation area
    assert "Inspection pass (ISO 14253-1 (k = 2)): no deviation area beyond [-0.500, 0.500] mm" in verdict
    assert "mounts: calibration" in verdict
    assert "aligned by best-fit" in verdict
    links = (("link-report", "/files/report.html"), ("link-e57", "/files/cloud.e57"), ("link-cloud", "/cloud"))
    for link, href in links:
        assert browser.find_element(By.ID, link).get_attribute("href").endswith(f"/v1/jobs/{job_id}{href}")
    report = httpx.get(cell.url + f"/v1/jobs/{job_id}/files/report.html")
    assert report.status_code == 200 and "Inspection report" in report.text
    points = int(browser.find_element(By.ID, "cloud-canvas").get_attribute("data-points"))
    assert 100_000 <= points <= 200_000
    # the default part's template: its characteristics over serials, this job the first
    wait(browser, lambda d: d.find_element(By.ID, "trend-svg").get_attribute("data-points"), 20)
    assert int(browser.find_element(By.ID, "trend-svg").get_attribute("data-points")) >= 1
    assert "serials, mean" in text(browser, "trend-text")
    ticks = text(browser, "colour-ticks")
    assert "-1.50" in ticks and "-0.50" in ticks and "+0.50" in ticks and "+1.50" in ticks  # 3x the +-0.5 mm band

    img = canvas_pixels(browser)
    drawn = np.abs(img - BACKGROUND_RGB).sum(axis=2) > 40
    assert drawn.mean() > 0.03, f"only {drawn.mean():.1%} of the canvas is drawn"
    r, g, b = (img[..., k][drawn] for k in range(3))
    # 96 % of the points are within the band: the in-band colours of the map (cyan-green-yellow) dominate
    assert np.mean((g >= r) & (g >= b)) > 0.6
    browser.execute_script("document.getElementById('result-panel').scrollIntoView({block: 'start'})")
    browser.save_screenshot(str(SCREENSHOTS / "console-3d-view.png"))
    ActionChains(browser).click_and_hold(browser.find_element(By.ID, "cloud-canvas")).move_by_offset(150, 40) \
        .release().perform()
    turned = np.abs(img - canvas_pixels(browser)).sum(axis=2) > 40
    assert turned.mean() > 0.01, "dragging did not turn the view"


def test_problem_json_shows_as_a_readable_message(cell, browser):
    sign_in(browser, cell.browser_url)
    wait(browser, lambda d: d.find_elements(By.CSS_SELECTOR, "#plan-select option"))
    browser.execute_script("document.querySelector('#plan-select option').value = 'no-such-plan'")
    browser.execute_script("document.getElementById('plan-select').selectedIndex = 0")
    click(browser, "submit-button")
    wait(browser, lambda d: visible(d, "message"), 10)
    assert text(browser, "message-text").startswith("Unknown plan: no plan named 'no-such-plan'")


@pytest.mark.parametrize("width,height,mobile", [(1280, 800, False), (820, 1180, True)])
def test_layout_fits_and_every_control_has_a_text_label(cell, browser, width, height, mobile):
    metrics(browser, width, height, mobile)
    try:
        sign_in(browser, cell.browser_url)
        wait(browser, lambda d: visible(d, "app"))
        overflow = browser.execute_script("return document.documentElement.scrollWidth - window.innerWidth")
        assert overflow <= 0, f"{overflow} px wider than the {width} px viewport"
        unlabelled = browser.execute_script("""
            return [...document.querySelectorAll('button, input, select, canvas')].filter((e) => {
              const own = (e.textContent || '').trim() || e.getAttribute('aria-label');
              const label = e.id && document.querySelector(`label[for="${e.id}"]`);
              return !(own || (label && label.textContent.trim()));
            }).map((e) => e.id || e.outerHTML.slice(0, 60));""")
        assert unlabelled == []
        stop = browser.find_element(By.ID, "stop-button")
        assert stop.is_displayed() and stop.size["height"] >= 40  # a stop a finger hits
    finally:
        metrics(browser, 1280, 800)
