"""Frames/s of `facepipe edit` while a handle is dragged, in headless Chromium and over the WebSocket.

    python -m bench.editor_speed --browser-model ict_model.npz --browser-take ict/train_mocap.csv \\
        --server-model model_530k.npz --server-take rig/take.csv --shots bench/editor -o bench/editor_speed.json

Frames/s are what a user sees: a brow handle is held and moved up and down with real mouse events
(DevTools Input events at 100 Hz, :func:`bench.editor_browser.mouse_drag_presented`) and the page's
animation frames that drew are counted. With them: the page's own stage timings (server round trip,
the worker's evaluation and normals, upload, render submission), the CPU each process and thread
used per presented frame (the machine's cores are shared: CPU per frame is what the stages cost,
frames/s what was left for them), and the time a draw of the scene takes in the GPU process.

Browser mode (a model whose B fits the page): screenshots before and after a drag (final and
details layers) go to ``--shots``, and the dragged frame's positions from the page are compared
with ``replay --edits``. Server mode (the paper's 530k): a WebSocket client drags a handle with two
requests in flight, as the page does, and counts the streamed frames per second; then the page.

``--label`` files the results under that key of the output JSON, keeping the others (before/after).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from bench.editor_browser import (browser_page, chromium_or_reason, drag, editor_server, mouse_drag_presented,
                                  save_edits, screenshot, wait_settled)

def page_measures(page, handle: int, pixels: float, server_pid: int | None, seconds: float = 8.0,
                  repeats: int = 1) -> dict:
    """Frames presented while the handle is dragged with the mouse (and where the time goes), then
    the same without drawing (what evaluation alone reaches), and a draw's cost in the GPU process.
    With ``repeats`` > 1 the drag is made that many times: ``mouse_drag`` is the median one by
    frames/s, ``mouse_drags`` the frames/s and load of each (on a shared machine one drag's figure
    moves with the others' load)."""
    start = page.evaluate(f"window.facepipeEditor.handleScreen({handle})")
    drags = [mouse_drag_presented(page, start, pixels, seconds, server_pid=server_pid) for _ in range(max(1, repeats))]
    out = {"mouse_drag": sorted(drags, key=lambda d: d["presented_fps"])[len(drags) // 2],
           "mouse_drags": [{"presented_fps": d["presented_fps"], "load_average_1min": d["load_average_1min"]}
                           for d in drags]}
    page.evaluate("window.facepipeEditor.state.noRender = true")
    without = mouse_drag_presented(page, start, pixels, seconds / 2, server_pid=server_pid)
    page.evaluate("window.facepipeEditor.state.noRender = false")
    out["mouse_drag_without_drawing"] = {k: without[k] for k in ("evaluations_per_s", "stage_ms", "load_average_1min")}
    if page.evaluate("typeof window.facepipeEditor.renderCost === 'function'"):
        out["draw_in_gpu_process_ms"] = page.evaluate("window.facepipeEditor.renderCost(10)")
    return out


def brow_handle(rest_handles: np.ndarray, names: list[str], up: np.ndarray) -> int:
    """A handle on a brow: the highest handle (along ``up``) among those a quarter of the face's
    width to the side of its middle, leaving out stable markers (named S…) on the skull."""
    width = np.ptp(rest_handles[:, 0])
    side = np.abs(rest_handles[:, 0] - np.median(rest_handles[:, 0])) / width
    ok = (side > 0.12) & (side < 0.3) & np.array([not n.startswith("S") for n in names])
    # the brow is below the forehead's top row: the highest 40 % of the face, its lowest handle there
    height = rest_handles @ up
    top = np.quantile(height[ok], 0.6)
    candidates = np.flatnonzero(ok & (height >= top))
    return int(candidates[np.argmin(height[candidates])])


def browser_mode(chromium: str, model_path: Path, take: Path, shots: Path, row: int, work: Path,
                 handle: str | None = None, pixels: float = 40, repeats: int = 1) -> dict:
    from facepipe.io.model_file import load_model

    model = load_model(model_path)
    rest = model.rest[model.handle_vertices].astype(np.float64)
    edits = work / "edits.json"
    with editor_server(model_path, take, "--edits", edits) as url, browser_page(chromium, url) as page:
        meta = page.evaluate("window.facepipeEditor.meta")
        up = np.array([0.0, 1.0, 0.0])
        h = meta["handle_names"].index(handle) if handle else brow_handle(rest, meta["handle_names"], up)
        page.evaluate(f"window.facepipeEditor.setFrame({row})")
        wait_settled(page)
        screenshot(page, shots / "browser_before.png")
        start = page.evaluate(f"window.facepipeEditor.handleScreen({h})")
        drag(page, start, 0, -pixels, steps=60)
        wait_settled(page)
        screenshot(page, shots / "browser_after.png")
        page.select_option("#layer", "details")
        wait_settled(page)
        screenshot(page, shots / "browser_after_details.png")
        page.select_option("#layer", "final")
        shown = np.array(page.evaluate("window.facepipeEditor.positions()")).reshape(-1, 3)
        save_edits(page)
        dragging = page_measures(page, h, pixels, server_pid=url.pid, repeats=repeats)
    out = work / "replay"
    subprocess.run([sys.executable, "-m", "facepipe", "replay", str(take), "-m", str(model_path), "-o", str(out),
                    "--edits", str(edits), "--backend", "numpy", "--head-motion", "remove", "-q"], check=True)
    replayed = np.load(out / "positions.npy")[row]
    return {"vertices": model.n_vertices, "handle": meta["handle_names"][h], "frame_row": row, **dragging,
            "page_vs_replay_max_abs": float(np.abs(shown - replayed).max()),
            "edits": json.loads(edits.read_text())["edits"]}


async def stream_drag(url: str, handle: int, seconds: float, amplitude: float) -> dict:
    """Drag ``handle`` over the WebSocket with two requests in flight; streamed frames per second."""
    import aiohttp

    async with aiohttp.ClientSession() as client, client.ws_connect(url.replace("http", "ws") + "ws",
                                                                        max_msg_size=0) as ws:
        await ws.receive()  # the edit state
        await ws.send_str(json.dumps({"op": "eval", "id": 0, "frame": 0}))
        await ws.receive()
        sent = answered = 0
        nbytes = base_bytes = 0
        clock = time.perf_counter()

        async def send():
            nonlocal sent
            sent += 1
            t = time.perf_counter() - clock
            offset = [0.0, amplitude * (1 - np.cos(t * 4)) / 2, 0.0]
            await ws.send_str(json.dumps({"op": "eval", "id": sent, "frame": 0,
                                          "preview": {"handle": handle, "offset": offset}}))

        await send()
        await send()
        first = None
        while time.perf_counter() - clock < seconds:
            msg = await ws.receive()
            data = msg.data
            head = np.frombuffer(data, "<f8", 6)
            if head[5] == 1:
                continue  # an unasked exact refinement
            if head[2] == 2:  # a new drag patch's base, ahead of its first step
                base_bytes = len(data)
                continue
            answered += 1
            nbytes += len(data)
            if first is None:  # the first answer builds the drag's patch: timed apart
                first = time.perf_counter() - clock
                answered, nbytes, clock = 0, 0, time.perf_counter()
            await send()
        seconds = time.perf_counter() - clock
    return {"streamed_fps": answered / seconds, "first_answer_s": first,
            "megabytes_per_frame": nbytes / max(answered, 1) / 1e6, "patch_base_megabytes": base_bytes / 1e6}


def server_stages(model, take: Path | None, handle: int, amplitude: float, steps: int = 10) -> dict:
    """Milliseconds of the server's share of a drag step at this size, in this process: the patch's
    evaluation (frames and details where B or the WPSD weights reach) and the message it makes."""
    from facepipe.cli.editor import _engine, prepared_take
    from facepipe.editor import server
    from facepipe.editor.session import EditorSession, rest_take

    evaluation_message = server.evaluation_message
    if hasattr(server, "drag_messages"):
        drag_messages = server.drag_messages
    else:  # an editor that sends whole frames while dragging (to compare with)
        def drag_messages(session, request, known=-1):
            return [evaluation_message(session, request)[0]]

    class Quiet:
        def __getattr__(self, name):
            return lambda *args, **kwargs: None

    session = EditorSession(model, prepared_take(take, model) if take else rest_take(model), Path("unused.json"),
                            mode="server")
    try:
        session.engine = _engine(model, "auto", Quiet())
        evaluation_message(session, {"op": "eval", "frame": 0}, exact=True)  # the page's first frame: its gate
        clock = time.perf_counter()
        drag_messages(session, {"op": "eval", "frame": 0, "preview": {"handle": handle, "offset": [0, 1e-3, 0]}})
        first = time.perf_counter() - clock
        known = getattr(session, "patch_serial", -1)  # the page has the patch's base: steps only
        patch = session._patch[1]
        evaluate, message = [], []
        for k in range(steps):
            offset = [0.0, amplitude * (k + 1) / steps, 0.0]
            clock = time.perf_counter()
            patch.evaluate_patch(offset) if hasattr(patch, "evaluate_patch") else patch.evaluate(offset)
            evaluate.append(time.perf_counter() - clock)
            clock = time.perf_counter()
            drag_messages(session, {"op": "eval", "frame": 0, "preview": {"handle": handle, "offset": offset}}, known)
            message.append(time.perf_counter() - clock)
        return {"engine": str(getattr(session.engine, "device", "cpu (numpy)")), "patch_vertices": len(patch.patch),
                "drag_start_s": first, "patch_evaluate_ms": 1000 * float(np.median(evaluate)),
                "step_message_ms": 1000 * float(np.median(message)),
                "load_average_1min": os.getloadavg()[0]}
    finally:
        session.close()


def server_mode(chromium: str | None, model_path: Path, take: Path | None, work: Path, with_page: bool = True) -> dict:
    from facepipe.io.model_file import load_model

    model = load_model(model_path)
    rest = model.rest[model.handle_vertices].astype(np.float64)
    h = brow_handle(rest, model.marker_names, np.array([0.0, 1.0, 0.0]))
    amplitude = float(np.median(model.rest_lengths)) * 0.5
    args = [model_path] + ([take] if take else []) + ["--edits", work / "edits530.json", "--evaluate", "server"]
    result = {"vertices": model.n_vertices, "handle": model.marker_names[h]}
    result["server_stages"] = server_stages(model, take, h, amplitude)
    print(json.dumps(result, indent=1), flush=True)
    with editor_server(*args, timeout=600) as url:
        result.update(asyncio.run(stream_drag(url, h, 8.0, amplitude)))
        if chromium and with_page:
            with browser_page(chromium, url) as page:
                wait_settled(page, timeout=600_000)
                result["page"] = page_measures(page, h, 20, server_pid=url.pid, seconds=15.0)
    return result


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--browser-model", type=Path)
    ap.add_argument("--browser-take", type=Path)
    ap.add_argument("--row", type=int, default=60, help="frame row of the browser-mode drag")
    ap.add_argument("--handle", default=None, help="browser mode: the handle to drag [default: a brow handle by "
                                                   "position]")
    ap.add_argument("--pixels", type=float, default=40, help="browser mode: how far to drag it up")
    ap.add_argument("--server-model", type=Path)
    ap.add_argument("--server-take", type=Path)
    ap.add_argument("--no-server-page", action="store_true", help="server mode: the WebSocket client only, not the page")
    ap.add_argument("--shots", type=Path, default=Path("bench/editor"))
    ap.add_argument("-o", "--output", type=Path, default=Path("bench/editor_speed.json"))
    ap.add_argument("--repeats", type=int, default=1, help="browser mode: drags measured (the median is reported)")
    ap.add_argument("--label", default=None, help="file the results under this key of the output, keeping the rest")
    a = ap.parse_args()
    chromium, reason = chromium_or_reason()
    results = {"chromium": chromium or reason, "cores": os.cpu_count(), "load_average_at_start": os.getloadavg()}
    a.shots.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix="editor-bench-") as work:
        if a.browser_model:
            if chromium is None:
                sys.exit(f"browser mode needs Chromium: {reason}")
            results["browser"] = browser_mode(chromium, a.browser_model, a.browser_take, a.shots, a.row, Path(work),
                                              a.handle, a.pixels, a.repeats)
            print(json.dumps(results["browser"], indent=1, default=str)[:1500], flush=True)
        if a.server_model:
            results["server"] = server_mode(chromium, a.server_model, a.server_take, Path(work),
                                            with_page=not a.no_server_page)
            print(json.dumps(results["server"], indent=1), flush=True)
    if a.label:
        kept = json.loads(a.output.read_text()) if a.output.is_file() else {}
        results = {**kept, a.label: results}
    a.output.write_text(json.dumps(results, indent=2, default=str))


if __name__ == "__main__":
    main()
