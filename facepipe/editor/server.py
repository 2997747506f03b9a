"""The editor's web server (aiohttp): the page, its own assets, the model bundle and a WebSocket.

Only the package's static folder and the session's data are served — no path on the command line
or elsewhere on disk is reachable through a URL. The WebSocket carries JSON requests from the page
and answers evaluations in binary (little-endian):

* pose terms (browser mode): float64 ``[id, row, 0, 0, exact, refine, handles (H·3), features (F),
  gate (F, with a gate)]``;
* positions (server mode): float64 ``[id, row, 1, layers, exact, refine, handles (H·3)]`` then
  float32 final (V·3) and, when ``layers`` is 2, the large scale (V·3).

``exact`` is 0 while the novelty gate's fits for a new pose are still running (the latest exact
gate stands in); an answer with ``refine`` 1 follows, unasked, with the exact evaluation of the
page's latest request once they are made. In server mode a drag meanwhile is evaluated on its
patch (:mod:`facepipe.editor.drag_patch`) and only the patch travels:

* a new patch: float64 ``[id, row, 2, layers, 0, 0, serial, n, handles (H·3)]``, then float32
  base final (V·3), base large (V·3), B's column of the handle (V), then uint32 patch vertices (n);
* each drag step: float64 ``[id, row, 3, layers, 0, 0, serial, n, handles (H·3), offset (3)]``,
  then float32 final of the patch's vertices (n·3); the page adds column × float32(offset) to the
  base everywhere (float32 arithmetic, as the server does) and puts the patch's positions over it.
"""

from __future__ import annotations

import asyncio
import json
import logging
from pathlib import Path
from urllib.parse import urlsplit

import numpy as np
from aiohttp import WSMsgType, web

from facepipe.core.edits import HandleEdit
from facepipe.editor.session import EditorSession

STATIC = Path(__file__).parent / "static"
SESSION = web.AppKey("session", EditorSession)
# how long the page's requests must pause before the gate's exact fits of the latest one start
PAUSE_SECONDS = 0.15
logger = logging.getLogger(__name__)


def _preview(session: EditorSession, request: dict) -> HandleEdit | None:
    """The uncommitted edit of a drag in progress, from the page's request (or None)."""
    drag = request.get("preview")
    if not drag:
        return None
    handle = int(drag["handle"])
    if not 0 <= handle < len(session.model.handle_vertices):
        raise ValueError(f"no handle {handle}")
    offset = tuple(float(v) for v in drag["offset"])
    if len(offset) != 3 or not np.all(np.isfinite(offset)):
        raise ValueError("an offset is three finite numbers")
    row = int(request["frame"])
    return HandleEdit(float(session.take.frames[row]), {handle: offset}, max(0.0, float(drag.get("ease_in", 0))),
                      max(0.0, float(drag.get("ease_out", 0))))


def evaluation_message(session: EditorSession, request: dict, exact: bool = False, refine: bool = False) -> tuple[bytes, bool]:
    """The binary answer to an ``eval`` request (see the module's docstring) and whether it is
    exact; with ``exact`` False it does not wait for the gate's fits of a new pose."""
    row = int(request["frame"])
    if not 0 <= row < len(session.take.frames):
        raise ValueError(f"no frame row {row}")
    preview = _preview(session, request)
    if session.mode == "browser":
        handles = session.handles(row, preview)
        features, gate, is_exact = session.pose_terms(handles, exact)
        head = [float(request.get("id", 0)), float(row), 0.0, 0.0, float(is_exact), float(refine)]
        parts = [np.array(head), handles.ravel(), features]
        if gate is not None:
            parts.append(gate)
        return np.concatenate(parts).astype("<f8").tobytes(), is_exact
    handles, final, large, is_exact = session.positions(row, preview, exact)
    layers = 1 if request.get("layer", "final") == "final" else 2
    head = [float(request.get("id", 0)), float(row), 1.0, float(layers), float(is_exact), float(refine)]
    out = [np.array(head).astype("<f8").tobytes(), handles.astype("<f8").tobytes(), final.astype("<f4").tobytes()]
    if layers == 2:
        out.append(large.astype("<f4").tobytes())
    return b"".join(out), is_exact


def drag_messages(session: EditorSession, request: dict, known_serial: int = -1) -> list[bytes] | None:
    """The answers to an ``eval`` request of a drag in server mode while the gate's exact fits
    are not made — the patch's base unless the page has it (``known_serial``: the serial of the
    last base sent to this page), then the step — or None (answer it whole)."""
    if session.mode != "server":
        return None
    row = int(request["frame"])
    if not 0 <= row < len(session.take.frames):
        raise ValueError(f"no frame row {row}")
    drag = session.drag_patch(row, _preview(session, request), exact=False)
    if drag is None:
        return None
    handles, patch, _, offset = drag
    new = known_serial != session.patch_serial
    layers = 1 if request.get("layer", "final") == "final" else 2
    n = len(patch.patch)
    ident = [float(request.get("id", 0)), float(row)]
    out = []
    if new:
        head = np.array(ident + [2.0, float(layers), 0.0, 0.0, float(session.patch_serial), float(n)], "<f8")
        out.append(b"".join([head.tobytes(), patch.base_handles.astype("<f8").tobytes(),
                             patch.base_final.astype("<f4").tobytes(), patch.base_large.astype("<f4").tobytes(),
                             patch.column.astype("<f4").tobytes(), patch.patch.astype("<u4").tobytes()]))
    head = np.array(ident + [3.0, float(layers), 0.0, 0.0, float(session.patch_serial), float(n)], "<f8")
    out.append(b"".join([head.tobytes(), handles.astype("<f8").tobytes(), np.asarray(offset, "<f8").tobytes(),
                         patch.evaluate_patch(offset).astype("<f4").tobytes()]))
    return out


class Refiner:
    """Sends the exact answer to the page's latest request once the gate's fits for it are made
    (in the background, newest request first; older ones are dropped)."""

    def __init__(self, session: EditorSession, ws: web.WebSocketResponse, send_lock: asyncio.Lock):
        self.session, self.ws, self.lock = session, ws, send_lock
        self.latest: dict | None = None
        self.task: asyncio.Task | None = None

    def request(self, req: dict) -> None:
        self.latest = req
        if self.task is None or self.task.done():
            self.task = asyncio.create_task(self._run())

    def seen(self, req: dict) -> None:
        """A newer request was answered exactly: nothing to refine."""
        self.latest = None

    async def _run(self) -> None:
        while self.latest is not None:
            req = self.latest
            # the fits take a core for a while: wait until the pointer pauses, so that a drag's
            # answers have the machine to themselves
            await asyncio.sleep(PAUSE_SECONDS)
            if self.latest is not req:
                continue
            session = self.session
            row = int(req["frame"])
            handles = session.handles(row, _preview(session, req))
            await asyncio.to_thread(session.exact_gate, handles)
            if self.latest is not req:  # the page has moved on: fit its newest pose instead
                continue
            message, _ = await asyncio.to_thread(evaluation_message, session, req, True, True)
            if self.latest is req and not self.ws.closed:
                async with self.lock:
                    await self.ws.send_bytes(message)
                self.latest = None


def _state(session: EditorSession, **extra) -> str:
    names, units = session.model.marker_names, session.model.meta.get("units")
    return json.dumps({"type": "state", **session.history.state(names, units), **extra})


def _edit_op(session: EditorSession, request: dict) -> str:
    """Apply a commit / undo / redo / clear / save request; the new state as JSON text."""
    op = request["op"]
    history = session.history
    if op == "commit":
        edit = _preview(session, request)
        if edit is None:
            raise ValueError("commit needs a preview edit")
        (handle, offset), = edit.offsets.items()
        history.add_offset(edit.frame, handle, offset, edit.ease_in, edit.ease_out)
    elif op == "undo":
        history.undo()
    elif op == "redo":
        history.redo()
    elif op == "clear":
        history.clear()
    elif op == "save":
        history.save(session.edits_path, session.model.marker_names, session.model.meta.get("units"))
        return _state(session, saved=str(session.edits_path))
    else:
        raise ValueError(f"unknown op {op!r}")
    return _state(session)


async def _socket(request: web.Request) -> web.WebSocketResponse:
    session = request.app[SESSION]
    # WebSockets are not bound by the same-origin policy: another site open in the same browser
    # could otherwise drive (and save) this session
    origin = request.headers.get("Origin")
    if origin is not None and urlsplit(origin).netloc != request.host:
        raise web.HTTPForbidden(text="the editor's WebSocket answers its own page only")
    ws = web.WebSocketResponse(max_msg_size=1 << 20)
    await ws.prepare(request)
    lock = asyncio.Lock()
    refiner = Refiner(session, ws, lock)
    await ws.send_str(_state(session))
    # requests are answered one at a time, in order; an answer without the gate's exact fits is
    # followed by the exact one when they are made, unless a newer request came first
    known_serial = -1  # the drag patch whose base this page has
    async for msg in ws:
        if msg.type != WSMsgType.TEXT:
            continue
        try:
            req = json.loads(msg.data)
            if req.get("op") == "eval":
                messages = await asyncio.to_thread(drag_messages, session, req, known_serial)
                exact = False
                if messages is not None:
                    known_serial = session.patch_serial
                if messages is None:
                    message, exact = await asyncio.to_thread(evaluation_message, session, req)
                    messages = [message]
                async with lock:
                    for message in messages:
                        await ws.send_bytes(message)
                refiner.seen(req) if exact else refiner.request(req)
            else:
                text = await asyncio.to_thread(_edit_op, session, req)
                async with lock:
                    await ws.send_str(text)
        except (ValueError, KeyError, TypeError, OSError) as exc:
            async with lock:
                await ws.send_str(json.dumps({"type": "error", "message": f"{exc.__class__.__name__}: {exc}"}))
    if refiner.task is not None:
        refiner.task.cancel()
    return ws


def make_app(session: EditorSession) -> web.Application:
    """The aiohttp application of one editing session."""
    app = web.Application()
    app[SESSION] = session
    bundle = {}

    async def index(_):
        return web.FileResponse(STATIC / "index.html", headers={"Cache-Control": "no-store"})

    async def model_bin(_):
        if "data" not in bundle:  # built once, on the first load
            bundle["data"] = await asyncio.to_thread(session.model_bundle)
        return web.Response(body=bundle["data"], content_type="application/octet-stream")

    async def truth(req):
        row = int(req.match_info["row"])
        if not 0 <= row < len(session.take.frames) or session.truth is None:
            raise web.HTTPNotFound()
        x = await asyncio.to_thread(session.truth_frame, row)
        return web.Response(body=x.astype("<f4").tobytes(), content_type="application/octet-stream")

    app.router.add_get("/", index)
    app.router.add_get("/api/model.bin", model_bin)
    app.router.add_get(r"/api/truth/{row:\d+}", truth)
    app.router.add_get("/ws", _socket)
    app.router.add_static("/static/", STATIC, show_index=False, follow_symlinks=False)
    return app


async def serve(session: EditorSession, host: str, port: int, announce) -> None:
    """Run the server until cancelled; ``announce(url)`` once it listens (port 0: a free port)."""
    runner = web.AppRunner(make_app(session), access_log=None)
    await runner.setup()
    site = web.TCPSite(runner, host, port)
    await site.start()
    sockets = site._server.sockets if site._server is not None else []
    actual = sockets[0].getsockname()[1] if sockets else port
    shown = f"[{host}]" if ":" in host else host
    announce(f"http://{shown}:{actual}/")
    try:
        await asyncio.Event().wait()
    finally:
        await runner.cleanup()
        session.close()
