"""Driving the editor page in headless Chromium (Playwright with the system's browser): used by the
browser test (tests/test_editor.py) and bench/editor_speed.py."""

from __future__ import annotations

import contextlib
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

# what works headless without a GPU: WebGL through SwiftShader, no network services
CHROMIUM_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                 "--disable-background-networking", "--disable-component-update", "--disable-sync",
                 "--use-angle=swiftshader", "--enable-unsafe-swiftshader"]
CHROMIUM_PATHS = ["/usr/bin/chromium", "/usr/bin/chromium-browser", "/usr/bin/google-chrome"]


def chromium_or_reason() -> tuple[str | None, str]:
    """The system's Chromium and Playwright, or (None, why not)."""
    try:
        import playwright.sync_api  # noqa: F401
    except ImportError:
        return None, "playwright is not installed (pip install playwright; no browser download is needed)"
    for path in [os.environ.get("FACEPIPE_CHROMIUM", "")] + CHROMIUM_PATHS + [shutil.which("chromium") or ""]:
        if path and os.access(path, os.X_OK):
            return path, ""
    return None, "no Chromium on this machine (apt-get install chromium, or set FACEPIPE_CHROMIUM)"


@contextlib.contextmanager
def editor_server(*args, timeout: float = 120.0):
    """Run `facepipe edit ARGS --port 0` and yield its address; stopped on exit."""
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    proc = subprocess.Popen([sys.executable, "-m", "facepipe", "edit", *map(str, args), "--port", "0"],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env)
    lines = []
    try:
        deadline = time.monotonic() + timeout
        url = None
        while url is None:
            line = proc.stdout.readline()
            if not line:
                raise RuntimeError("facepipe edit stopped:\n" + "".join(lines))
            lines.append(line)
            match = re.search(r"open (http://\S+)", line)
            url = match.group(1) if match else None
            if time.monotonic() > deadline:
                raise RuntimeError("facepipe edit did not print its address:\n" + "".join(lines))
        yield url
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()


@contextlib.contextmanager
def browser_page(chromium: str, url: str, size=(900, 700)):
    """A page of a fresh headless Chromium (own profile folder) at the editor, once it has drawn."""
    from playwright.sync_api import sync_playwright

    with tempfile.TemporaryDirectory(prefix="facepipe-chromium-") as profile, sync_playwright() as p:
        context = p.chromium.launch_persistent_context(profile, executable_path=chromium, args=CHROMIUM_ARGS,
                                                       headless=True, viewport={"width": size[0], "height": size[1]})
        try:
            page = context.pages[0] if context.pages else context.new_page()
            errors = []
            page.on("pageerror", lambda e: errors.append(str(e)))
            page.goto(url)
            page.wait_for_function("window.facepipeEditor && window.facepipeEditor.ready", timeout=120_000)
            page.errors = errors
            yield page
        finally:
            context.close()


def wait_idle(page, timeout: float = 60_000) -> None:
    """Until the page has no evaluation in flight or pending (and has drawn the last answer)."""
    page.wait_for_function("window.facepipeEditor.idle", timeout=timeout)
    page.evaluate("() => new Promise(r => requestAnimationFrame(() => r()))")


def wait_settled(page, timeout: float = 120_000) -> None:
    """Until the page shows the exact evaluation of its latest request (the gate's fits made)."""
    page.wait_for_function("window.facepipeEditor.settled", timeout=timeout)
    page.evaluate("() => new Promise(r => requestAnimationFrame(() => r()))")


def drag(page, start: dict, dx: float, dy: float, steps: int = 20, shift: bool = False) -> float:
    """Drag with real mouse events from ``start`` (page pixels) by (dx, dy); the page's frames/s
    over the drag (each move asks for an evaluation; the page keeps one in flight)."""
    page.mouse.move(start["x"], start["y"])
    if shift:
        page.keyboard.down("Shift")
    page.mouse.down()
    t0 = page.evaluate("window.facepipeEditor.state.evaluations")
    clock = time.perf_counter()
    for k in range(1, steps + 1):  # as fast as the events go: the page drops moves it cannot keep up with
        page.mouse.move(start["x"] + dx * k / steps, start["y"] + dy * k / steps)
    page.wait_for_function("window.facepipeEditor.idle")
    seconds = time.perf_counter() - clock
    frames = page.evaluate("window.facepipeEditor.state.evaluations") - t0
    page.mouse.up()
    if shift:
        page.keyboard.up("Shift")
    wait_idle(page)
    return frames / seconds if seconds > 0 else float("nan")


def screenshot(page, path: Path):
    page.screenshot(path=str(path))
    import imageio.v3 as iio

    return iio.imread(path)[..., :3].astype(float)


def save_edits(page) -> None:
    page.click("#save")
    page.wait_for_function("document.getElementById('message').textContent.startsWith('saved')")
