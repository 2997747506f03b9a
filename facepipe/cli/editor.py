"""`facepipe edit`: load the model and take, then serve the editor page until interrupted."""

from __future__ import annotations

import asyncio
from pathlib import Path

import numpy as np

from facepipe.editor.session import EditorSession, Take, rest_take
from facepipe.errors import InputError
from facepipe.io.edits_file import read_edits
from facepipe.io.model_file import load_model
from facepipe.mocap import read_take
from facepipe.mocap.prepare import PrepareOptions, prepare_take_windows


def prepared_take(path, model, take_units: str | None = None) -> Take:
    """The take prepared exactly as ``facepipe replay`` prepares it with its defaults (aligned,
    stabilised, cleaned), all windows joined: the page's frames are replay's rows."""
    take = read_take(path, model.marker_names, units=model.meta.get("units"), take_units=take_units,
                     absent="missing", allow_empty_frames=True)
    prepared = prepare_take_windows(take, model, PrepareOptions())
    heads, rotations, translations = [], [], []
    for head, R, t in prepared.windows():
        heads.append(head)
        rotations.append(R)
        translations.append(t)
    return Take(np.concatenate(heads), np.concatenate(rotations), np.concatenate(translations),
                np.asarray(take.frames), np.asarray(take.times), Path(path).name)


def _engine(model, backend: str, rep):
    """The server-mode evaluator: OpenCL when it works (or is asked for), else NumPy."""
    from facepipe.cli.commands import _make_evaluator

    return _make_evaluator(model, backend, None, 1, rep)


def edit_command(rep, model_path, take_path, edits_path, host: str, port: int, truth_path, mode: str,
                 backend: str, take_units: str | None) -> None:
    model = load_model(model_path)
    if edits_path is None:
        edits_path = Path(take_path).with_suffix(".edits.json") if take_path else Path("edits.json")
    edits_path = Path(edits_path)
    edits = read_edits(edits_path, model.marker_names, model.meta.get("units")) if edits_path.is_file() else []
    if truth_path is not None and take_path is None:
        raise InputError("--truth needs a TAKE: the truth is matched to the take's frames")
    take = prepared_take(take_path, model, take_units) if take_path else rest_take(model)
    if port < 0 or port > 65535:
        raise InputError(f"--port {port} is not a TCP port (0 picks a free one)")
    session = EditorSession(model, take, edits_path, edits, mode=mode, truth_path=truth_path)
    if session.mode == "server":
        session.engine = _engine(model, backend, rep)
    rep.say(f"{model.n_vertices} vertices, {len(take.frames)} frames of {take.name}; "
            f"{len(edits)} edits from {edits_path}" if edits else
            f"{model.n_vertices} vertices, {len(take.frames)} frames of {take.name}; edits save to {edits_path}")
    rep.say(f"evaluation: {session.meta()['engine']}")
    if host not in ("127.0.0.1", "localhost", "::1"):
        rep.say(f"warning: listening on {host}: anyone who can reach this machine can edit and save")

    def announce(url):
        # the address goes out even with --quiet: it is what the command is for
        print(f"facepipe edit: open {url}  (Ctrl+C stops)", flush=True)

    from facepipe.editor.server import serve

    try:
        asyncio.run(serve(session, host, port, announce))
    except OSError as exc:
        raise InputError(f"cannot listen on {host}:{port}: {exc.strerror or exc}",
                         hint="choose another --port (0 picks a free one)") from None
