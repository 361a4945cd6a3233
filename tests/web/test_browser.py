"""The page in a real browser (Debian's headless chromium through chromium-driver): opened with the
token, it calibrates (the "holder is empty" confirm stands in for the press), starts a measurement
on the twin, waits for the result page with its plot, overlays it with a re-fit, and saves screenshots (to
$TRIMETER_SCREENSHOT_DIR if set — docs/img holds the project's — else the test's temporary directory).
All of it under the page's Content-Security-Policy: the browser must report no violation of it, and the
stylesheet and the script-set colours must have taken effect."""

from __future__ import annotations

import os
from pathlib import Path


from browser_support import click_live, csp_violations, needs_browser
from conftest import web_instrument
from hil_support import SAMPLE, THICKNESS_MM

pytestmark = needs_browser


def test_the_page_calibrates_measures_and_shows_the_result(tmp_path, browser):
    from selenium.webdriver.common.by import By
    from selenium.webdriver.support import expected_conditions as EC
    from selenium.webdriver.support.ui import WebDriverWait

    shots = Path(os.environ.get("TRIMETER_SCREENSHOT_DIR") or tmp_path)
    shots.mkdir(parents=True, exist_ok=True)
    wait = WebDriverWait(browser, 120)

    console: list[dict] = []  # every browser console entry (get_log drains it)
    with web_instrument(tmp_path / "rig") as web:
        web.twin.control.remove_sample()
        browser.get(f"{web.url}/?token={web.token}")
        assert "token" not in browser.current_url  # taken once, then a cookie
        header = browser.find_element(By.TAG_NAME, "header")
        assert header.value_of_css_property("background-color") == "rgba(29, 35, 48, 1)"  # style.css applied
        wait.until(EC.text_to_be_present_in_element((By.ID, "state"), "Empty the holder"))
        click_live(wait, (By.ID, "holder-empty"))
        wait.until(EC.text_to_be_present_in_element((By.ID, "state"), "Ready"))
        web.twin.control.insert_sample(SAMPLE, THICKNESS_MM)
        label = browser.find_element(By.NAME, "label")
        label.send_keys("cyan-ink")
        wait.until(EC.text_to_be_present_in_element((By.ID, "conn"), "live"))
        browser.save_screenshot(str(shots / "web-status.png"))
        browser.find_element(By.ID, "measure-btn").click()
        wait.until(EC.url_contains("#/m/"))
        wait.until(EC.presence_of_element_located((By.CSS_SELECTOR, "#m-plot svg path")))
        assert "cyan-ink" in browser.find_element(By.ID, "m-title").text
        assert browser.find_elements(By.CSS_SELECTOR, "#m-files a")
        browser.save_screenshot(str(shots / "web-measurement.png"))
        measured = browser.current_url.rsplit("/", 1)[1]
        assert (web.history.root / measured / "parameters.csv").exists()

        refit = web.call("POST", f"/api/measurements/{measured}/refit", {"maps": ["device-n1.5-l0.4"]})
        other = web.wait_job(refit.json["job"]["id"])["measurement"]
        browser.get(f"{web.url}/#/compare/{measured}/{other}")
        wait.until(EC.presence_of_element_located((By.CSS_SELECTOR, "#c-plot svg path")))
        assert len(browser.find_elements(By.CSS_SELECTOR, "#c-legend a")) == 2
        swatches = browser.find_elements(By.CSS_SELECTOR, "#c-legend i")
        assert [s.value_of_css_property("background-color") for s in swatches] == ["rgba(35, 100, 210, 1)",
                                                                                   "rgba(210, 105, 30, 1)"]
        console += browser.get_log("browser")
        browser.save_screenshot(str(shots / "web-overlay.png"))

        browser.get(f"{web.url}/#/history")
        wait.until(EC.presence_of_element_located((By.CSS_SELECTOR, "#rows tr")))
        assert measured in browser.find_element(By.ID, "rows").get_attribute("innerHTML")
        browser.save_screenshot(str(shots / "web-history.png"))
        console += browser.get_log("browser")
    assert not csp_violations(console), csp_violations(console)
    for name in ("web-status.png", "web-measurement.png", "web-overlay.png", "web-history.png"):
        assert (shots / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
