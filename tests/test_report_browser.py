"""The report page in a real headless browser (Debian's chromium + chromium-driver, installed by scripts/run.sh)."""

import json
import shutil
import tempfile

import pytest
from selenium import webdriver
from selenium.webdriver.chrome.service import Service
from selenium.webdriver.common.by import By

import mitsuba_shsampling  # noqa: F401  (LLVM backend check)
import mitsuba as mi

mi.set_variant("llvm_ad_rgb")

from mitsuba_shsampling import cli, scenes  # noqa: E402

#: Flags that work on a closed network, as root, without a GPU.
CHROMIUM_FLAGS = ("--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                  "--disable-background-networking", "--disable-component-update", "--disable-sync",
                  "--window-size=1400,1024")


def chromium_paths() -> tuple[str, str]:
    browser = shutil.which("chromium") or shutil.which("chromium-browser")
    driver = shutil.which("chromedriver")
    if not (browser and driver):
        pytest.fail("chromium and chromedriver are needed: apt-get install -y chromium chromium-driver "
                    "(scripts/run.sh does this)")
    return browser, driver


@pytest.fixture(scope="module")
def report_page(tmp_path_factory):
    out = tmp_path_factory.mktemp("report")
    code = cli.main(["compare", scenes.builtin_scenes()["sphere_ggx010"], "--out", str(out), "--res", "16",
                     "--spp", "2", "--passes", "4", "--ref-spp", "16", "--sampler", "independent",
                     "--methods", "direct,direct_misc,env_only,sh_direct,sh_product_only",
                     "--convergence-max-spp", "2",
                     "--cache-dir", str(out / "cache"), "--no-progress"])
    assert code == 0
    return out


@pytest.fixture(scope="module")
def browser():
    binary, driver_path = chromium_paths()
    profile = tempfile.mkdtemp(prefix="chromium-profile-")
    options = webdriver.ChromeOptions()
    options.binary_location = binary
    for flag in CHROMIUM_FLAGS + (f"--user-data-dir={profile}",):
        options.add_argument(flag)
    driver = webdriver.Chrome(service=Service(driver_path), options=options)
    try:
        yield driver
    finally:
        driver.quit()
        shutil.rmtree(profile, ignore_errors=True)


def test_verdict_table_is_visible_first_with_one_row_per_scene_and_sampler(report_page, browser):
    browser.get((report_page / "index.html").as_uri())
    table = browser.find_element(By.ID, "verdict")
    assert table.is_displayed()
    rows = table.find_elements(By.TAG_NAME, "tr")[1:]
    report = json.loads((report_page / "report.json").read_text())
    assert len(rows) == len(report["verdict"]) == 1
    cells = rows[0].find_elements(By.TAG_NAME, "td")
    assert [c.text for c in cells[:3]] == ["sphere_ggx010", "independent", "direct"]
    # First the plugin at its defaults against the best Mitsuba strategy, then the other configurations.
    assert [c.find_element(By.TAG_NAME, "b").text for c in cells[3:5]] == ["sh_direct (defaults)"] * 2
    assert "direct" in report["verdict"][0]["equal_spp"]["denominator"]
    others = browser.find_element(By.ID, "verdict-others").find_elements(By.TAG_NAME, "tr")[1:]
    assert [r.find_element(By.TAG_NAME, "b").text for r in others] == [
        "sh_direct (strategy=product_only)"]
    # Nothing but the title and the verdict heading comes before it.
    assert table.location["y"] < browser.find_element(By.TAG_NAME, "details").location["y"]


def test_the_page_fits_1400_px_and_names_the_environment_map_beside_its_thumbnail(report_page, browser):
    browser.set_window_size(1400, 1024)
    browser.get((report_page / "index.html").as_uri())
    viewport = browser.execute_script("return document.documentElement.clientWidth;")
    assert viewport <= 1400
    assert browser.execute_script("return document.documentElement.scrollWidth;") <= viewport
    for table in browser.find_elements(By.TAG_NAME, "table"):
        assert table.rect["x"] + table.rect["width"] <= viewport, table.get_attribute("id")
        if not table.get_attribute("id").startswith("verdict"):
            # A metrics row is one line of text: no cell (a tail flag) wraps into a tall row.
            line = browser.execute_script("return parseFloat(getComputedStyle(arguments[0]).fontSize);", table)
            assert max(row.rect["height"] for row in table.find_elements(By.TAG_NAME, "tr")[1:]) < 2.2 * line
    envmap = browser.find_element(By.CLASS_NAME, "envmap")
    assert envmap.is_displayed() and "Environment map: sunsky.exr" in envmap.text
    thumbnail = envmap.find_element(By.TAG_NAME, "img")
    assert browser.execute_script("return arguments[0].naturalWidth;", thumbnail) > 0


def test_every_method_has_a_zoomed_crop_at_the_same_place(report_page, browser):
    browser.get((report_page / "index.html").as_uri())
    crops = browser.find_elements(By.CSS_SELECTOR, ".crop img")
    report = json.loads((report_page / "report.json").read_text())
    assert len(crops) == 2 * len(report["scenes"][0]["runs"][0]["methods"])  # equal samples, equal time
    offsets = {(c.value_of_css_property("margin-left"), c.value_of_css_property("margin-top")) for c in crops}
    assert len(offsets) == 1


def test_every_image_on_the_page_loads(report_page, browser):
    browser.get((report_page / "index.html").as_uri())
    loaded = browser.execute_script(
        "return Array.from(document.images).map(i => [i.alt, i.complete, i.naturalWidth]);")
    assert len(loaded) >= 10  # reference, renders at equal spp and time, maps, convergence
    for alt, complete, width in loaded:
        assert complete and width > 0, alt


def test_settings_are_collapsed_at_the_bottom(report_page, browser):
    browser.get((report_page / "index.html").as_uri())
    details = browser.find_element(By.TAG_NAME, "details")
    assert not details.get_attribute("open")
    assert not browser.find_element(By.CSS_SELECTOR, "details pre").is_displayed()
    details.find_element(By.TAG_NAME, "summary").click()
    assert "llvm_ad_rgb" in browser.find_element(By.CSS_SELECTOR, "details pre").text
