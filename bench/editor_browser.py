"""Driving the editor page in headless Chromium (Playwright with the system's browser): used by the
browser test (tests/test_editor.py) and bench/editor_speed.py."""

from __future__ import annotations

import asyncio
import contextlib
import json
import math
import os
import re
import shutil
import socket
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

# frames presented, counted the same way whatever the page's code: an animation frame (the
# browser's display cycle, which it slows when drawing falls behind) in which the page issued
# WebGL draws is a presented frame; several draws in one cycle show as one
PRESENTED_COUNTER_JS = """(() => {
  const counter = { frames: 0, ticks: 0 };
  let drew = false;
  for (const Context of [window.WebGLRenderingContext, window.WebGL2RenderingContext]) {
    if (!Context) continue;
    for (const name of ['drawElements', 'drawArrays', 'drawElementsInstanced', 'drawArraysInstanced']) {
      const draw = Context.prototype[name];
      if (draw) Context.prototype[name] = function (...args) { drew = true; return draw.apply(this, args); };
    }
  }
  const tick = () => { counter.ticks += 1; if (drew) { counter.frames += 1; drew = false; } requestAnimationFrame(tick); };
  requestAnimationFrame(tick);
  window.__presented = counter;
})();"""


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


class ServerAddress(str):
    """The editor's address; ``pid``: its server's process."""

    pid: int


@contextlib.contextmanager
def editor_server(*args, timeout: float = 120.0):
    """Run `facepipe edit ARGS --port 0` and yield its address (a :class:`ServerAddress`);
    stopped on exit."""
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
        address = ServerAddress(url)
        address.pid = proc.pid
        yield address
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@contextlib.contextmanager
def browser_page(chromium: str, url: str, size=(900, 700)):
    """A page of a fresh headless Chromium (own profile folder) at the editor, once it has drawn;
    ``page.debug_port``: the browser's DevTools port on 127.0.0.1 (see :func:`stream_mouse`)."""
    from playwright.sync_api import sync_playwright

    port = _free_port()
    with tempfile.TemporaryDirectory(prefix="facepipe-chromium-") as profile, sync_playwright() as p:
        context = p.chromium.launch_persistent_context(profile, executable_path=chromium,
                                                       args=CHROMIUM_ARGS + [f"--remote-debugging-port={port}"],
                                                       headless=True, viewport={"width": size[0], "height": size[1]})
        try:
            page = context.pages[0] if context.pages else context.new_page()
            page.debug_port = port
            errors = []
            page.on("pageerror", lambda e: errors.append(str(e)))
            page.add_init_script(PRESENTED_COUNTER_JS)
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


def _proc_stat(path: str) -> tuple[str, int, float] | None:
    """(name, parent pid, CPU seconds) of /proc/PID/stat or /proc/PID/task/TID/stat."""
    try:
        text = Path(path).read_text()
    except OSError:
        return None
    name = text[text.index("(") + 1:text.rindex(")")]
    fields = text[text.rindex(")") + 2:].split()
    return name, int(fields[1]), (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _role(pid: int, server_pid: int | None, descends) -> str | None:
    try:
        cmd = Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
    except OSError:
        return None
    if server_pid is not None and descends(pid, server_pid):
        return "server (python)"
    if not descends(pid, os.getpid()):
        return None
    if "--type=gpu-process" in cmd:
        return "chromium gpu process (SwiftShader)"
    if "--type=renderer" in cmd:
        return "chromium renderer"
    if "chrom" in cmd:
        return "chromium browser and utilities"
    if "node" in cmd or "playwright" in cmd:
        return "playwright driver"
    return None


def cpu_by_role(server_pid: int | None = None) -> dict[str, float]:
    """CPU seconds used so far by the editor's server, Chromium's processes (the renderer's and the
    GPU process's by thread name) and the test driver: differences of two of these over a drag say
    where its time goes."""
    stats = {int(p): _proc_stat(f"/proc/{p}/stat") for p in os.listdir("/proc") if p.isdigit()}
    parent = {pid: st[1] for pid, st in stats.items() if st}

    def descends(pid, root):
        for _ in range(64):
            if pid == root:
                return True
            pid = parent.get(pid, 0)
            if pid <= 1:
                return False
        return False

    out: dict[str, float] = {}
    for pid, st in stats.items():
        role = st and _role(pid, server_pid, descends)
        if role is None:
            continue
        if role not in ("chromium renderer", "chromium gpu process (SwiftShader)"):
            out[role] = out.get(role, 0.0) + st[2]
            continue
        for tid in os.listdir(f"/proc/{pid}/task"):  # by thread: the main thread, the worker, …
            thread = _proc_stat(f"/proc/{pid}/task/{tid}/stat")
            if thread is None:
                continue
            name = "main thread" if int(tid) == pid else "worker (evaluation)" if "Worker" in thread[0] else thread[0]
            out[f"{role}: {name}"] = out.get(f"{role}: {name}", 0.0) + thread[2]
    return out


PAGE_COUNTERS_JS = """() => {
  const ed = window.facepipeEditor, s = ed.state;
  return { t: performance.now(), presented: window.__presented.frames, ticks: window.__presented.ticks,
           evaluations: s.evaluations, sums: { ...(s.stageSums || {}) }, counts: { ...(s.stageCounts || {}) } };
}"""


async def _stream_moves(port: int, start: dict, pixels: float, seconds: float, hz: float) -> int:
    """Left-button mouse moves up and down by ``pixels`` from ``start``, ``hz`` a second for
    ``seconds``, sent as DevTools Input events without waiting for each to be acknowledged (as a
    mouse does: Playwright's mouse.move waits for the browser's next frame, which would pace the
    pointer by the page it measures); the number sent."""
    import aiohttp

    async with aiohttp.ClientSession() as client:
        targets = await (await client.get(f"http://127.0.0.1:{port}/json/list")).json()
        url = next(t["webSocketDebuggerUrl"] for t in targets if t["type"] == "page")
        async with client.ws_connect(url, max_msg_size=0) as ws:
            async def drain():
                async for _ in ws:
                    pass

            reader = asyncio.create_task(drain())
            clock, moves = time.perf_counter(), 0
            while (t := time.perf_counter() - clock) < seconds:
                moves += 1
                y = start["y"] - pixels * (1 - math.cos(2 * math.pi * t / 1.5)) / 2
                await ws.send_str(json.dumps({"id": moves, "method": "Input.dispatchMouseEvent", "params": {
                    "type": "mouseMoved", "x": start["x"], "y": y, "button": "left", "buttons": 1}}))
                await asyncio.sleep(max(0.0, clock + moves / hz - time.perf_counter()))
            reader.cancel()
            return moves


def stream_mouse(page, start: dict, pixels: float, seconds: float, hz: float = 100.0) -> int:
    """:func:`_stream_moves` on the page's browser, from a thread of its own (the sync Playwright
    API holds this thread's event loop)."""
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(1) as pool:
        return pool.submit(asyncio.run, _stream_moves(page.debug_port, start, pixels, seconds, hz)).result()


def mouse_drag_presented(page, start: dict, pixels: float, seconds: float, hz: float = 100.0,
                         server_pid: int | None = None) -> dict:
    """Hold the handle at ``start`` and move it with real mouse events (``hz`` a second, like a
    mouse) up and down by ``pixels`` for ``seconds``; what the page presented meanwhile: frames/s
    (animation frames with a draw), evaluations/s and the mean milliseconds of each of its stages."""
    page.mouse.move(start["x"], start["y"])
    page.mouse.down()
    page.mouse.move(start["x"], start["y"] - 2)
    wait_idle(page)  # the drag's first answer (in server mode: its patch's base) off the clock
    before = page.evaluate(PAGE_COUNTERS_JS)
    cpu0, load0 = cpu_by_role(server_pid), os.getloadavg()[0]
    moves = stream_mouse(page, start, pixels, seconds, hz)
    cpu1 = cpu_by_role(server_pid)
    after = page.evaluate(PAGE_COUNTERS_JS)
    page.mouse.up()
    wait_idle(page)
    page.keyboard.press("Control+z")  # the drag committed an edit: undone, the handle is back at start
    wait_idle(page)
    span = (after["t"] - before["t"]) / 1000
    stages = {k: (after["sums"][k] - before["sums"].get(k, 0)) / (after["counts"][k] - before["counts"].get(k, 0))
              for k in after["sums"] if after["counts"][k] > before["counts"].get(k, 0)}
    frames = max(after["presented"] - before["presented"], 1)
    cpu = {role: {"cores": (cpu1[role] - cpu0.get(role, 0.0)) / span,
                  "ms_per_presented_frame": 1000 * (cpu1[role] - cpu0.get(role, 0.0)) / frames} for role in cpu1}
    return {"presented_fps": (after["presented"] - before["presented"]) / span,
            "load_average_1min": [load0, os.getloadavg()[0]], "cpu": cpu,
            "animation_frames_per_s": (after["ticks"] - before["ticks"]) / span,
            "evaluations_per_s": (after["evaluations"] - before["evaluations"]) / span,
            "mouse_moves_per_s": moves / span, "seconds": span, "stage_ms": stages}


def screenshot(page, path: Path):
    page.screenshot(path=str(path))
    import imageio.v3 as iio

    return iio.imread(path)[..., :3].astype(float)


def save_edits(page) -> None:
    page.click("#save")
    page.wait_for_function("document.getElementById('message').textContent.startsWith('saved')")
