"""The system's Chromium, headless, driven by selenium through the system's chromedriver (Debian: apt-get install
chromium chromium-driver): for the watch page's browser test and benchmarks/watch_overhead.py."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path
from typing import Any

CHROMIUM, CHROMEDRIVER = "/usr/bin/chromium", "/usr/bin/chromedriver"
FLAGS = (
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--window-size=1400,2000",
)
# the page's header text (qmg_lab/watch/page.py), '' until Bokeh has loaded the document
HEADER_JS = """
if (!window.Bokeh || !Bokeh.documents || !Bokeh.documents.length) return '';
const h = Bokeh.documents[0].get_model_by_name('header'); return h ? h.text : '';
"""


def missing() -> str:
    """Why no headless Chromium can be started here ('' if it can)."""
    try:
        import selenium  # noqa: F401
    except ImportError:
        return "selenium is not installed"
    for exe in (CHROMIUM, CHROMEDRIVER):
        if not os.access(exe, os.X_OK):
            return f"{exe} is not installed (apt-get install chromium chromium-driver; .ci/run does)"
    return ""


def headless_chromium(tmp_dir: Path) -> Any:
    """A selenium WebDriver of a headless Chromium with a new empty profile under tmp_dir, its console logged."""
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    options.binary_location = CHROMIUM
    for flag in (*FLAGS, f"--user-data-dir={tempfile.mkdtemp(dir=tmp_dir)}"):
        options.add_argument(flag)
    options.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    return webdriver.Chrome(service=Service(CHROMEDRIVER), options=options)
