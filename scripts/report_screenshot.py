"""A screenshot of a report page's first screen (the README's and docs/REPORT.md's picture).

    python scripts/report_screenshot.py report/ -o docs/report.png [--width 1400] [--height 1000]

Opens ``REPORT_DIR/index.html`` in Debian's headless chromium (the browser the report's tests
use, installed by ``scripts/run.sh test``) at the given window size and saves what it shows.
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("report", metavar="REPORT_DIR")
    parser.add_argument("-o", "--out", default="docs/report.png")
    parser.add_argument("--width", type=int, default=1400)
    parser.add_argument("--height", type=int, default=1000)
    args = parser.parse_args()
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    browser = shutil.which("chromium") or shutil.which("chromium-browser")
    driver_path = shutil.which("chromedriver")
    if not browser or not driver_path:
        print("chromium and chromedriver are needed: apt-get install -y chromium chromium-driver", file=sys.stderr)
        return 1
    page = os.path.join(os.path.abspath(args.report), "index.html")
    if not os.path.exists(page):
        print(f"{page}: no report page there (run compare first)", file=sys.stderr)
        return 1
    profile = tempfile.mkdtemp(prefix="chromium-profile-")
    options = webdriver.ChromeOptions()
    options.binary_location = browser
    for flag in ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
                 f"--window-size={args.width},{args.height}", f"--user-data-dir={profile}"):
        options.add_argument(flag)
    driver = webdriver.Chrome(service=Service(driver_path), options=options)
    try:
        driver.get("file://" + page)
        os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
        driver.save_screenshot(args.out)
    finally:
        driver.quit()
        shutil.rmtree(profile, ignore_errors=True)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
