"""The report's 3D page checked in a real browser: headless Chromium (Debian's ``chromium`` and
``chromium-driver``, which ``make setup`` installs) driven by selenium.

:func:`check_scene_page` loads ``scene.html`` from ``file://`` and reports what a reviewer
would meet: the console's errors, every request the page made (a self-contained page makes none
but to ``file:`` and ``data:``), whether moving the slider changes the 3D view (the canvas,
pixel for pixel) and the camera images (the overlay videos' times), and what hovering an object
shows (the mouse put where the objects' markers are drawn: the canvas with them and without).
"""

from __future__ import annotations

import io
import shutil
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from selenium.webdriver.chrome.webdriver import WebDriver
    from selenium.webdriver.remote.webelement import WebElement

CHROMIUM = "/usr/bin/chromium"
CHROMEDRIVER = "/usr/bin/chromedriver"


def browser_available() -> bool:
    """Whether headless Chromium and its driver are installed."""
    driver = Path(CHROMEDRIVER).exists() or shutil.which("chromedriver") is not None
    return Path(CHROMIUM).exists() and driver


@dataclass(frozen=True)
class PageCheck:
    """What the browser met on the page."""

    load_s: float
    console_errors: list[str]
    requests_away: list[str]
    frames: tuple[str, str]  # the frame shown before and after moving the slider
    canvas_changed: bool
    video_times: tuple[list[float], list[float]]  # the overlays' times before and after
    hover: str  # the hover label's text over an object ('' where none showed)


def _driver() -> WebDriver:
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    opts = webdriver.ChromeOptions()
    opts.binary_location = CHROMIUM
    for a in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage", "--enable-unsafe-swiftshader",
              "--use-angle=swiftshader", "--window-size=1600,1000", "--mute-audio"):
        opts.add_argument(a)
    opts.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    driver = shutil.which("chromedriver") or CHROMEDRIVER
    return webdriver.Chrome(service=Service(driver), options=opts)


def check_scene_page(page: Path, timeout_s: float = 60.0) -> PageCheck:
    """Load ``page`` in headless Chromium and try it as a reviewer would (see the module)."""
    from PIL import Image
    from selenium.webdriver.common.action_chains import ActionChains
    from selenium.webdriver.common.by import By

    d = _driver()
    try:
        t0 = time.perf_counter()
        d.get(Path(page).resolve().as_uri())
        while time.perf_counter() - t0 < timeout_s:
            if d.execute_script(
                    "return document.getElementById('frame-shown') !== null && "
                    "document.getElementById('frame-shown').textContent !== ''"):
                break
            time.sleep(0.1)
        load = time.perf_counter() - t0
        canvas = d.find_element(By.CSS_SELECTOR, "#scene .gl-container canvas")

        def shot() -> np.ndarray:
            return np.asarray(Image.open(io.BytesIO(canvas.screenshot_as_png)).convert("RGB")).astype(int)

        def state() -> tuple[str, list[float]]:
            return (str(d.execute_script("return document.getElementById('frame-shown').textContent")),
                    [float(t) for t in d.execute_script(
                        "return Array.from(document.querySelectorAll('video')).map(v => v.currentTime)")])

        f0, v0 = state()
        before = shot()
        rail = d.find_element(By.CSS_SELECTOR, "#scene .slider-rail-rect")
        ActionChains(d).move_to_element_with_offset(rail, int(rail.size["width"] * 0.3), 0).click().perform()
        time.sleep(1.0)
        f1, v1 = state()
        after = shot()
        hover = _hover(d, canvas, shot)
        logs = d.get_log("browser")
        errors = [str(e.get("message", "")) for e in logs if e.get("level") == "SEVERE"]
        urls = d.execute_script(
            "return performance.getEntriesByType('resource').map(e => e.name)")
        away = [u for u in urls if not str(u).startswith(("file:", "data:", "blob:"))]
        return PageCheck(load, errors, away, (f0, f1), bool(np.any(before != after)), (v0, v1), hover)
    finally:
        d.quit()


def _hover(d: WebDriver, canvas: WebElement, shot: Callable[[], np.ndarray]) -> str:
    """The hover label over one of the objects' markers (the last trace), '' where none showed."""
    from selenium.webdriver.common.action_chains import ActionChains

    n = int(d.execute_script("return document.getElementById('scene').data.length"))
    with_m = shot()
    restyle = "Plotly.restyle(document.getElementById('scene'), {visible: %s}, [%d])"
    d.execute_script(restyle % ("false", n - 1))
    time.sleep(0.5)
    without = shot()
    d.execute_script(restyle % ("true", n - 1))
    time.sleep(0.5)
    ys, xs = np.nonzero(np.abs(with_m - without).sum(axis=2) > 60)
    w, h = canvas.size["width"], canvas.size["height"]
    for k in np.linspace(0, len(xs) - 1, min(len(xs), 25)).astype(int) if len(xs) else []:
        x, y = int(xs[k]) - w // 2, int(ys[k]) - h // 2
        ActionChains(d).move_to_element_with_offset(canvas, x, y).perform()
        time.sleep(0.3)
        text = str(d.execute_script("return Array.from(document.querySelectorAll('#scene .hovertext'))"
                                    ".map(h => h.textContent).join(' ')"))
        if "id" in text:
            return text
    return ""
