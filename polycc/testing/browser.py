"""A real headless Chromium (Debian's ``chromium``) driven by Playwright, for page tests.

Playwright's own browser download does not work here; ``launch(executable_path=...)`` drives the system
Chromium instead. Software WebGL (SwiftShader) draws three.js pages without a GPU.
"""

from __future__ import annotations

import os
import shutil
import tempfile
import time

CHROMIUM_FLAGS = ["--no-sandbox", "--disable-gpu", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
                  "--disable-quic", "--no-first-run", "--disable-background-networking", "--disable-component-update",
                  "--disable-sync"]


def chromium_path() -> str | None:
    return os.environ.get("POLYCC_CHROMIUM") or shutil.which("chromium") or shutil.which("chromium-browser")


class Page:
    """``with Page(url) as p: p.shot(path)``; ``p.page`` is the Playwright page, ``p.console`` its log."""

    def __init__(self, url: str, width: int = 1280, height: int = 800, timeout_s: float = 60.0):
        self.url, self.size, self.timeout_ms = url, {"width": width, "height": height}, int(timeout_s * 1000)
        self.console: list[str] = []

    def __enter__(self) -> "Page":
        from playwright.sync_api import sync_playwright

        self._profile = tempfile.mkdtemp(prefix="polycc-chromium-")
        self._pw = sync_playwright().start()
        self._ctx = self._pw.chromium.launch_persistent_context(
            self._profile, executable_path=chromium_path(), headless=True, args=CHROMIUM_FLAGS, viewport=self.size)
        self.page = self._ctx.new_page()
        self.page.on("console", lambda m: self.console.append(m.text))
        self.page.goto(self.url, wait_until="load", timeout=self.timeout_ms)
        self.page.wait_for_selector("canvas", timeout=self.timeout_ms)
        return self

    def wait_for_text_gone(self, text: str, timeout_s: float = 60.0) -> None:
        t0 = time.monotonic()
        while time.monotonic() - t0 < timeout_s:
            if text not in self.page.inner_text("body"):
                return
            time.sleep(0.25)
        raise TimeoutError(f"the page still shows {text!r} after {timeout_s:g} s")

    def wait_for_text(self, *texts: str, timeout_s: float = 60.0) -> str:
        """The page's text once it shows every one of ``texts`` (a connected viser client receives its GUI
        after the "Connected" notice, later on a loaded host); TimeoutError naming the missing ones."""
        t0 = time.monotonic()
        while True:
            body = self.page.inner_text("body")
            missing = [t for t in texts if t not in body]
            if not missing:
                return body
            if time.monotonic() - t0 > timeout_s:
                raise TimeoutError(f"the page does not show {missing} after {timeout_s:g} s; it shows "
                                   f"{body[:300]!r}")
            time.sleep(0.25)

    def png(self) -> bytes:
        return self.page.screenshot(timeout=self.timeout_ms)

    def shot(self, path) -> None:
        self.page.screenshot(path=str(path), timeout=self.timeout_ms)

    def __exit__(self, *exc) -> None:
        try:
            self._ctx.close()
        finally:
            self._pw.stop()
            shutil.rmtree(self._profile, ignore_errors=True)
