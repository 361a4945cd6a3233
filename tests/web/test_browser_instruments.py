"""Several instruments on the page, in a real browser (as test_browser.py): the Instruments panel lists the three
twins on one bus with their state, one is calibrated and measured from its row, and the history tags the result
with that instrument. Under the page's Content-Security-Policy, with no violation reported."""

from __future__ import annotations

from browser_support import click_live, csp_violations, needs_browser
from hil_support import SAMPLE, THICKNESS_MM
from lab_support import NAMES, served_lab

pytestmark = needs_browser


def test_the_page_shows_every_instrument_and_measures_on_one_of_them(tmp_path, browser):
    from selenium.webdriver.common.by import By
    from selenium.webdriver.support.ui import WebDriverWait

    wait = WebDriverWait(browser, 120)

    def row_text(name: str) -> str:  # read in one script: the panel re-renders its rows every few seconds
        return browser.execute_script(
            "const r = document.querySelector(`#instruments tr[data-instrument='${arguments[0]}']`);"
            "return r ? r.textContent : '';", name)

    def measurement_of(name: str) -> str:
        return browser.execute_script(
            "const a = document.querySelector(`#instruments tr[data-instrument='${arguments[0]}'] a[href^='#/m/']`);"
            "return a ? a.textContent : '';", name)
    with served_lab(tmp_path) as (page, twins, results):
        browser.get(f"{page.url}/?token={page.token}")
        wait.until(lambda d: len(d.find_elements(By.CSS_SELECTOR, "#instruments tr")) == 3)
        names = browser.execute_script(
            "return [...document.querySelectorAll('#instruments tr')].map((r) => r.dataset.instrument);")
        assert names == list(NAMES)
        wait.until(lambda d: "Empty the holder" in row_text("right"))
        click_live(wait, (By.XPATH, "//tr[@data-instrument='right']//button[text()='Holder is empty']"))
        wait.until(lambda d: "Ready" in row_text("right"))
        assert "Empty the holder" in row_text("left")  # the others untouched
        twins["right"].control.insert_sample(SAMPLE, THICKNESS_MM)
        click_live(wait, (By.XPATH, "//tr[@data-instrument='right']//button[text()='Measure']"))
        wait.until(lambda d: measurement_of("right"))
        measured = measurement_of("right")
        assert (results / measured / "parameters.csv").exists()
        browser.save_screenshot(str(tmp_path / "web-instruments.png"))

        browser.get(f"{page.url}/#/history")
        wait.until(lambda d: d.find_elements(By.CSS_SELECTOR, "#rows tr"))
        cells = [c.text for c in browser.find_elements(By.CSS_SELECTOR, "#rows tr td")]
        assert "right" in cells
        console = browser.get_log("browser")
    assert not csp_violations(console), csp_violations(console)
