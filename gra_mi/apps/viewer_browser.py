"""The viewer's page in headless Chromium, driven through its own controls as a user drives it: the browser test of
`gra-mi view` (tests/test_viewer.py) and its latency benchmark (benchmarks/viewer.py). Needs selenium (the ``dev``
extra) and Chromium with its driver (scripts/setup.sh installs them with apt)."""

from __future__ import annotations

import contextlib
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from gra_mi.core.shard import free_port


def chromium() -> tuple[str, str] | None:
    browser = shutil.which("chromium") or shutil.which("chromium-browser") or shutil.which("google-chrome")
    driver = shutil.which("chromedriver")
    return (browser, driver) if browser and driver else None


class Page:
    """The viewer's page in headless Chromium, driven through its own controls."""

    def __init__(self, url: str):
        from selenium import webdriver
        from selenium.webdriver.chrome.service import Service

        browser, driver = chromium()
        options = webdriver.ChromeOptions()
        for flag in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage", "--window-size=1000,700", "--use-angle=swiftshader",
                     "--enable-unsafe-swiftshader"):  # fmt: skip
            options.add_argument(flag)
        options.binary_location = browser
        self.driver = webdriver.Chrome(service=Service(driver), options=options)
        self.driver.get(url)
        self.view = self.wait_for_view(None, timeout=120)

    def control(self, label: str):
        from selenium.webdriver.common.by import By

        found = [e for e in self.driver.find_elements(By.TAG_NAME, "label") if e.text == label]
        if not found:
            raise LookupError(f"no control labelled {label!r}")
        return self.driver.find_element(By.ID, found[0].get_attribute("for"))

    def choose(self, label: str, option: str) -> float:
        from selenium.webdriver.common.by import By

        self.control(label).click()
        time.sleep(0.3)
        [e for e in self.driver.find_elements(By.CSS_SELECTOR, "[role=option]") if e.text == option][0].click()
        return time.perf_counter()

    def press(self, label: str, key: str, times: int) -> float:
        field = self.control(label)
        field.click()
        for _ in range(times):
            field.send_keys(key)
        return time.perf_counter()

    def timings_text(self) -> str | None:
        return self.driver.execute_script(
            "const p = Array.from(document.querySelectorAll('p')).find(e => e.textContent.startsWith('view ')); return p ? p.textContent : null;"
        )

    def wait_for_view(self, previous: str | None, timeout: float = 60.0) -> str:
        """Wait until the server has sent a view newer than ``previous`` (its counter is in the timings line)."""
        deadline = time.perf_counter() + timeout
        while time.perf_counter() < deadline:
            text = self.timings_text()
            if text and text != previous:
                return text
            time.sleep(0.02)
        raise TimeoutError(f"no new view within {timeout} s (last: {previous})")

    def settle(self, since: float) -> float:
        """Wait for the views a change asked for to stop coming; the browser-observed latency of the first one."""
        first = self.wait_for_view(self.view)
        latency = time.perf_counter() - since
        self.view = first
        self.quiet()
        return latency

    def quiet(self) -> None:
        """Wait until no new view has come for 1.5 s."""
        while True:
            try:
                self.view = self.wait_for_view(self.view, timeout=1.5)
            except TimeoutError:
                return

    def shot(self, path: Path) -> np.ndarray:
        """A screenshot (written to ``path``) once the page has drawn the last image (two in a row the same: software
        WebGL is slow)."""
        import imageio.v3 as iio

        path.parent.mkdir(parents=True, exist_ok=True)
        previous = None
        # Chromium's software WebGL makes viser pin a notice over the canvas: out of the picture.
        self.driver.execute_script("document.querySelectorAll('.mantine-Notification-root').forEach(e => e.remove());")
        for _ in range(25):
            time.sleep(0.2)
            self.driver.save_screenshot(str(path))
            image = iio.imread(path)[..., :3]
            if previous is not None and np.array_equal(image[:, :600], previous[:, :600]):
                return image
            previous = image
        return previous


@contextlib.contextmanager
def viewer_in_browser(scene: Path, uv_resolution: int):
    """`gra-mi view SCENE` in a process of its own, and its page open in headless Chromium."""
    port = free_port()
    server = subprocess.Popen(
        [sys.executable, "-m", "gra_mi.cli", "view", "--scene", str(scene), "--uv-resolution", str(uv_resolution), "--port", str(port),
         "--seconds", "900"],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env={**os.environ, "GRA_MI_QUIET": "1"},
    )  # fmt: skip
    page = None
    try:
        for line in server.stdout:
            if "open http://" in line:
                break
        page = Page(f"http://127.0.0.1:{port}")
        page.quiet()  # the first views (and the background trace's) have come: changes are timed from here
        yield page
    finally:
        if page is not None:
            page.driver.quit()
        server.terminate()
        server.wait(timeout=30)
