"""The play page in a real headless browser (Debian's chromium through selenium), for the page's test and
benchmarks/bench_play.py."""
import shutil
from typing import Tuple


def headless_chromium() -> Tuple[object, str]:
    """(a headless chromium webdriver, "") or (None, the reason) where chromium, chromedriver or selenium is
    missing."""
    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    driver = shutil.which("chromedriver")
    if not chromium or not driver:
        return None, ("no headless browser: install Debian's chromium and chromium-driver (.ci/run does) to run the "
                      "page in a real browser")
    try:
        from selenium import webdriver
    except ImportError:
        return None, "selenium is not installed (pip install -e .[test])"
    options = webdriver.ChromeOptions()
    options.binary_location = chromium
    for flag in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage", "--disable-gpu"):
        options.add_argument(flag)
    return webdriver.Chrome(options=options, service=webdriver.ChromeService(executable_path=driver)), ""
