"""A real headless browser for the tests of the people's pages: Debian's chromium driven through its chromedriver
(/usr/bin/chromedriver, installed by the project's set-up for tests: .ci/run), with selenium from PyPI. Nothing is
downloaded at run time: selenium is given the driver's path, so its manager never runs."""

from __future__ import annotations

import shutil
import socket
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

CHROMEDRIVER = Path("/usr/bin/chromedriver")
FLAGS = (
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
)


def browser(width: int = 412, height: int = 1400) -> Any:
    """A headless chromium of a phone's width (412 px, a tall window so a screenshot holds the whole page), or the
    test skips saying what is missing."""
    webdriver = pytest.importorskip("selenium.webdriver", reason="selenium is not installed (requirements-dev.txt)")
    from selenium.webdriver.chrome.service import Service

    if not CHROMEDRIVER.exists() or shutil.which("chromium") is None:
        pytest.skip("Debian's chromium and chromium-driver are not installed (.ci/run installs them)")
    opts = webdriver.ChromeOptions()
    for flag in FLAGS:
        opts.add_argument(flag)
    opts.add_argument(f"--window-size={width},{height}")
    opts.binary_location = shutil.which("chromium") or ""
    return webdriver.Chrome(service=Service(executable_path=str(CHROMEDRIVER)), options=opts)


def free_port() -> int:
    """A TCP port free on this machine now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def wait_until(what: Callable[[], Any], timeout: float, why: str, said: Callable[[], str] = lambda: "") -> Any:
    """Wait for `what()` to be truthy and return it; fail naming `why` after `timeout` seconds."""
    end = time.monotonic() + timeout
    while True:
        try:
            got = what()
        except Exception:
            got = None
        if got:
            return got
        assert time.monotonic() < end, f"timed out after {timeout} s waiting for {why}\n{said()[-2000:]}"
        time.sleep(0.05)
