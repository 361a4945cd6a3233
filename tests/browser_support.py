"""The page's browser tests' shared parts: Debian's headless chromium through chromium-driver (skipped where
either is missing), a click on an element the page may rebuild, and the console's Content-Security-Policy
violations."""

from __future__ import annotations

import shutil

import pytest

CHROMIUM, DRIVER = shutil.which("chromium"), shutil.which("chromedriver")
needs_browser = pytest.mark.skipif(not (CHROMIUM and DRIVER),
                                   reason="needs Debian's chromium and chromium-driver (tools/setup.sh installs them)")


def chrome(window_size: str = "1280,1000"):
    """A headless chromium at `window_size` (one pixel a CSS pixel, for screenshots), keeping every console
    entry (CSP violations land there); the caller quits it."""
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    options.binary_location = CHROMIUM
    for arg in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage", f"--window-size={window_size}",
                "--disable-gpu", "--force-device-scale-factor=1"):
        options.add_argument(arg)
    options.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    driver = webdriver.Chrome(service=Service(executable_path=DRIVER), options=options)
    driver.set_page_load_timeout(30)
    return driver


def click_live(wait, locator) -> None:
    """Click an element that the page may rebuild at any moment (each status update re-renders the
    calibration prompt and the instruments' rows): retried until a click lands on an element still in the page."""
    from selenium.common.exceptions import StaleElementReferenceException

    def attempt(driver) -> bool:
        try:
            element = driver.find_element(*locator)
            if not (element.is_displayed() and element.is_enabled()):
                return False
            element.click()
            return True
        except StaleElementReferenceException:
            return False

    wait.until(attempt)


def csp_violations(console: list[dict]) -> list[str]:
    """The Content-Security-Policy violations among browser console entries (driver.get_log("browser"))."""
    return [e["message"] for e in console if "Content Security Policy" in e["message"]]
