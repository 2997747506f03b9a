"""The editor's web server (aiohttp): the page, its own assets, the model bundle and a WebSocket.

Only the package's static folder and the session's data are served — no path on the command line
or elsewhere on disk is reachable through a URL. The WebSocket carries JSON requests from the page
and answers evaluations in binary (little-endian):

* pose terms (browser mode): float64 ``[id, row, 0, 0, handles (H·3), features (F), gate (F, with a gate)]``;
* positions (server mode): float64 ``[id, row, 1, layers, handles (H·3)]`` then float32 final
  (V·3) and, when ``layers`` is 2, the large scale (V·3).
"""

from __future__ import annotations

import asyncio
import json
import logging
from pathlib import Path

import numpy as np
from aiohttp import WSMsgType, web

from facepipe.core.edits import HandleEdit
from facepipe.editor.session import EditorSession

STATIC = Path(__file__).parent / "static"
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


def evaluation_message(session: EditorSession, request: dict) -> bytes:
    """The binary answer to an ``eval`` request (see the module's docstring)."""
    row = int(request["frame"])
    if not 0 <= row < len(session.take.frames):
        raise ValueError(f"no frame row {row}")
    handles = session.handles(row, _preview(session, request))
    head = [float(request.get("id", 0)), float(row)]
    if session.mode == "browser":
        features, gate = session.pose_terms(handles)
        parts = [np.array(head + [0.0, 0.0]), handles.ravel(), features]
        if gate is not None:
            parts.append(gate)
        return np.concatenate(parts).astype("<f8").tobytes()
    final, large = session.evaluate(handles)
    layers = 1 if request.get("layer", "final") == "final" else 2
    out = [np.array(head + [1.0, float(layers)]).astype("<f8").tobytes(), handles.astype("<f8").tobytes(),
           final.astype("<f4").tobytes()]
    if layers == 2:
        out.append(large.astype("<f4").tobytes())
    return b"".join(out)


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
    session: EditorSession = request.app["session"]
    ws = web.WebSocketResponse(max_msg_size=1 << 20)
    await ws.prepare(request)
    await ws.send_str(_state(session))
    # one request at a time, in order: the page keeps at most one evaluation in flight
    async for msg in ws:
        if msg.type != WSMsgType.TEXT:
            continue
        try:
            req = json.loads(msg.data)
            if req.get("op") == "eval":
                await ws.send_bytes(await asyncio.to_thread(evaluation_message, session, req))
            else:
                await ws.send_str(await asyncio.to_thread(_edit_op, session, req))
        except (ValueError, KeyError, TypeError, OSError) as exc:
            await ws.send_str(json.dumps({"type": "error", "message": f"{exc.__class__.__name__}: {exc}"}))
    return ws


def make_app(session: EditorSession) -> web.Application:
    """The aiohttp application of one editing session."""
    app = web.Application()
    app["session"] = session
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
