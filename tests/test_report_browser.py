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


def rgb(element) -> tuple[int, int, int, float]:
    """The computed background colour of ``element`` as (r, g, b, alpha)."""
    values = element.value_of_css_property("background-color").split("(")[1].rstrip(")").split(",")
    return (*(int(v) for v in values[:3]), float(values[3]) if len(values) > 3 else 1.0)


def is_green(colour) -> bool:
    return colour[3] > 0 and colour[1] > colour[0] + 20


def is_red(colour) -> bool:
    return colour[3] > 0 and colour[0] > colour[1] + 20


def is_neutral(colour) -> bool:
    return colour[3] == 0 or abs(colour[0] - colour[1]) <= 20


def test_every_method_name_of_the_verdict_is_defined_on_the_page_at_1400_px(report_page, browser):
    browser.set_window_size(1400, 1024)
    browser.get((report_page / "index.html").as_uri())
    definitions = browser.find_element(By.ID, "methods")
    assert definitions.is_displayed()
    viewport = browser.execute_script("return document.documentElement.clientWidth;")
    assert definitions.rect["x"] + definitions.rect["width"] <= viewport
    terms = [dt.text for dt in definitions.find_elements(By.TAG_NAME, "dt")]
    texts = dict(zip(terms, (dd.text for dd in definitions.find_elements(By.TAG_NAME, "dd"))))
    report = json.loads((report_page / "report.json").read_text())
    named = {c[k] for row in report["verdict"] for c in (row["equal_spp"], row["equal_time"])
             for k in ("numerator", "denominator", "winner")}
    ran = set(report["scenes"][0]["runs"][0]["methods"])
    assert named <= ran and set(terms) == ran | {"best Mitsuba"}
    assert "direct (defaults)" in texts["direct_misc"] and "mis_compensation=true" in texts["direct_misc"]
    assert "emitter_samples=2, bsdf_samples=0" in texts["env_only"]
    assert all(text.strip() for text in texts.values())
    # With the verdict, above "How to read this page" and the scenes.
    assert definitions.location["y"] < browser.find_elements(By.TAG_NAME, "h2")[1].location["y"]


def test_wins_are_green_losses_red_and_ties_neutral_in_the_verdict_and_per_material(report_page, browser):
    """The saved report with known intervals put in: a clear loss (0.833x [0.725, 0.953] the
    efficiency) is as visible as a win, and a per-material 1.00 inside its interval is not red."""
    import dataclasses

    from mitsuba_shsampling.report.html import write_html
    from mitsuba_shsampling.report.schema import load_report

    report = load_report(report_page / "report.json")
    row = report.verdict[0]
    row.equal_spp = dataclasses.replace(row.equal_spp, ratio=0.8, low=0.7, high=0.9)
    row.equal_time = dataclasses.replace(row.equal_time, ratio=0.833, low=0.725, high=0.953)
    row.time_normalised = dataclasses.replace(row.time_normalised, ratio=1.0, low=0.95, high=1.05)
    rows = report.scenes[0].runs[0].materials["direct"]
    for material, (ratio, low, high) in zip(rows, [(1.0, 0.98, 1.02), (0.5, 0.4, 0.6), (2.0, 1.5, 2.5)]):
        material.error_ratio["sh_direct"] = {"equal_spp": ratio, "equal_time": ratio}
        material.error_ratio_interval["sh_direct"] = {"equal_spp": [low, high], "equal_time": [low, high]}
    write_html(str(report_page / "colours.html"), report)

    browser.set_window_size(1400, 1024)
    browser.get((report_page / "colours.html").as_uri())
    cells = browser.find_element(By.ID, "verdict").find_elements(By.TAG_NAME, "tr")[1].find_elements(By.TAG_NAME, "td")
    win, loss, tie = cells[3:6]
    assert is_green(rgb(win)) and "wins" in win.text
    assert is_red(rgb(loss)) and "loses" in loss.text and "0.833x" in loss.text
    assert is_neutral(rgb(tie)) and "tie" in tie.text and "best" not in tie.text
    tables = browser.find_elements(By.XPATH, "//h4[starts-with(., 'Per material')]/following-sibling::div[1]//table")
    header = tables[0].find_element(By.TAG_NAME, "tr").text
    assert "sh_direct: error ratio to the best Mitsuba there, equal samples" in header
    assert "sh_direct: error ratio, equal time" in header
    for title, check, text in (("tie:", is_neutral, "1"), ("wins:", is_green, "0.5"), ("loses:", is_red, "2")):
        shown = [c for c in tables[0].find_elements(By.CSS_SELECTOR, f"td[title^='{title}']") if c.text == text]
        assert len(shown) == 2 and all(check(rgb(c)) for c in shown), title
