"""C3D takes, read and written through ezc3d.

What is used: the 3D points, POINT:LABELS (continued in LABELS2, LABELS3, ... past 255
markers), POINT:UNITS, POINT:RATE, the header's first frame, and the residuals: a residual
below zero (or a non-finite coordinate) is a missing sample. Frame times are frame / rate.

A damaged C3D can crash the C3D library itself (a truncated file ends the process with a
segmentation fault), which would take the whole replay down without a message. Where the
platform can fork, the file is therefore read in a child process, and a child that dies
becomes an :class:`~facepipe.errors.InputError` naming the file.
"""

from __future__ import annotations

import os
import pickle
import signal
from pathlib import Path

import numpy as np

from facepipe.io.atomic import atomic_path
from facepipe.errors import InputError
from facepipe.mocap.markers import find_markers, normalise_units
from facepipe.mocap.registry import Format, nominal_rate, frames_from_rate, marker_label, register
from facepipe.mocap.take import Take

_HINT = "export the take from the capture software again (C3D, 3D points)"


def _labels(point: dict) -> list[str]:
    """POINT:LABELS followed by LABELS2, LABELS3, ... (C3D keeps 255 names per parameter)."""
    names = list(point.get("LABELS", {}).get("value", []))
    k = 2
    while f"LABELS{k}" in point:
        names += list(point[f"LABELS{k}"]["value"])
        k += 1
    return [str(n).strip() for n in names]


def _load(path: str) -> dict:
    """Everything this module needs from a C3D file, as plain arrays (runs in the child)."""
    import ezc3d  # lazily: only C3D takes need it (start-up)

    c = ezc3d.c3d(path, extract_forceplat_data=False)
    point = c["parameters"]["POINT"]
    data = c["data"]
    points = np.asarray(data["points"], dtype=np.float64)  # (4, N, T)
    residuals = np.asarray(data["meta_points"]["residuals"], dtype=np.float64) if "meta_points" in data else None
    units = point.get("UNITS", {}).get("value", [])
    rate = point.get("RATE", {}).get("value", [])
    return {
        "labels": _labels(point),
        "units": str(units[0]).strip() if len(units) else None,
        "rate": float(rate[0]) if len(rate) else float(c["header"]["points"]["frame_rate"]),
        "first_frame": int(c["header"]["points"]["first_frame"]),
        "points": points[:3] if points.ndim == 3 else np.zeros((3, 0, 0)),
        "residuals": None if residuals is None or residuals.size == 0 else residuals[0],
    }


def _isolated(fn, *args):
    """Run ``fn(*args)`` in a forked child and return its result; a crash becomes an InputError."""
    if not hasattr(os, "fork"):
        return fn(*args)
    read_fd, write_fd = os.pipe()
    pid = os.fork()
    if pid == 0:  # child: never returns
        status = 0
        try:
            # die of a crash rather than run a handler inherited from the parent (faulthandler,
            # a Python-level handler that would let the child carry on)
            for sig in (signal.SIGSEGV, signal.SIGBUS, signal.SIGFPE, signal.SIGILL, signal.SIGABRT):
                signal.signal(sig, signal.SIG_DFL)
            os.close(read_fd)
            try:
                payload = pickle.dumps(("ok", fn(*args)), protocol=pickle.HIGHEST_PROTOCOL)
            except BaseException as exc:  # noqa: BLE001 - reported to the parent
                payload = pickle.dumps(("error", f"{exc.__class__.__name__}: {exc}"))
            view = memoryview(payload)
            while view:
                view = view[os.write(write_fd, view):]
        except BaseException:  # noqa: BLE001
            status = 1
        finally:
            os._exit(status)
    os.close(write_fd)
    chunks = []
    with os.fdopen(read_fd, "rb") as fh:
        while True:
            chunk = fh.read(1 << 20)
            if not chunk:
                break
            chunks.append(chunk)
    _, status = os.waitpid(pid, 0)
    if os.WIFSIGNALED(status):
        sig = os.WTERMSIG(status)
        name = signal.Signals(sig).name if sig in signal.Signals._value2member_map_ else str(sig)
        raise InputError(f"the C3D file is damaged (the C3D library crashed reading it: {name})",
                         path=args[0], hint=_HINT)
    try:
        kind, value = pickle.loads(b"".join(chunks))
    except Exception:
        raise InputError("the C3D file could not be read", path=args[0], hint=_HINT) from None
    if kind != "ok":
        raise InputError(f"not a readable C3D file ({value})", path=args[0], hint=_HINT)
    return value


def _check_header(path: Path) -> None:
    """The C3D header: its key byte, and a file long enough for the frames it announces.

    The C3D library reads a truncated file without complaint (zeros) or crashes on it, so
    the sizes are checked here first: parameter section and data blocks within the file, and
    at least 2 bytes (integer storage; 4 for float) per point coordinate, residual and analog
    sample of every frame from the header's first to last frame.
    """
    try:
        size = path.stat().st_size
        with open(path, "rb") as fh:
            head = fh.read(512)
            fh.seek(max(0, (head[0] - 1) * 512) if head else 0)
            param = fh.read(4)
    except OSError as exc:
        raise InputError(f"cannot read the take: {exc.strerror or exc}", path=path) from None
    if not head:
        raise InputError("the take is empty", path=path, hint=_HINT)
    if len(head) < 512 or head[1] != 0x50 or head[0] < 2:
        raise InputError("not a C3D file (no C3D header)", path=path,
                         hint="a .c3d take must be a C3D file; for a CSV give it the .csv suffix")
    if len(param) < 4 or (head[0] - 1) * 512 + 512 > size:
        raise InputError("the C3D file is cut off before its parameters", path=path, hint=_HINT)
    order = ">" if param[3] == 86 else "<"  # 84 Intel, 85 DEC (little-endian words), 86 MIPS
    words = np.frombuffer(head[:24], dtype=f"{order}u2")
    n_points, n_analog, first, last, data_start = (int(words[1]), int(words[2]), int(words[3]), int(words[4]),
                                                   int(words[8]))
    scale = float(np.frombuffer(head[12:16], dtype=f"{order}f4")[0]) if param[3] != 85 else 1.0
    per = 4 if scale < 0 else 2
    frames = last - first + 1 if last >= first else 0  # >65535 frames wrap: no check then
    need = (max(data_start, 1) - 1) * 512 + frames * (4 * n_points + n_analog) * per
    if data_start < 2 or need > size:
        raise InputError(
            f"the C3D file is truncated: its header announces {frames} frames of {n_points} points "
            f"({need} bytes), the file has {size} bytes",
            path=path, hint=_HINT)


def read_c3d_take(path: Path, marker_names: list[str], match=None) -> Take:
    """Read every frame of a C3D take.

    Parameters
    ----------
    path : Path
    marker_names : list[str]
        The rig's M markers, in order.
    match : callable(list[str]) -> MarkerMatch, optional

    Returns
    -------
    Take
        ``positions`` (T, M, 3) float64 in the file's POINT:UNITS (``units`` set), NaN
        where the residual is negative; frames from the header's first frame, times
        frame / POINT:RATE.

    Raises
    ------
    InputError
        Not a C3D file, a damaged one, no rate, labels not matching the points.
    """
    path = Path(path)
    _check_header(path)
    raw = _isolated(_load, str(path))
    points, labels = raw["points"], raw["labels"]
    n_points = points.shape[1]
    if len(labels) < n_points:  # unnamed points can only be extras
        labels = labels + [f"(unnamed point {k + 1})" for k in range(len(labels), n_points)]
    labels = labels[:n_points]
    rate = raw["rate"]
    if not np.isfinite(rate) or rate <= 0:
        raise InputError(f"POINT:RATE is {rate}: the frame rate is missing", path=path, hint=_HINT)
    units = normalise_units(raw["units"], path, "unit (POINT:UNITS)")
    found = find_markers(labels, marker_names, path, match)
    T = points.shape[2]
    positions = np.full((T, len(marker_names), 3), np.nan)
    present = found.index >= 0
    if T:
        positions[:, present] = points[:, found.index[present]].transpose(2, 1, 0)
        if raw["residuals"] is not None:
            gone = raw["residuals"][found.index[present]].T < 0  # (T, M')
            sub = positions[:, present]
            sub[gone] = np.nan
            positions[:, present] = sub
    frames, times = frames_from_rate(raw["first_frame"], T, rate)
    return Take(frames=frames, times=times, positions=positions, marker_names=list(marker_names), path=str(path),
                extra_markers=found.extra, units=units, markers=found.report)


def write_c3d_take(path, take: Take, units: str | None = None, subject: str | None = None) -> None:
    """Write a take as C3D (float points; missing samples get residual -1), atomically.

    Parameters
    ----------
    path : str or Path
    take : Take
        Frames must be consecutive (C3D stores a first frame and a rate only).
    units : str, optional
        POINT:UNITS to declare (default ``take.units`` or ``mm``).
    subject : str, optional
        Prefix marker labels with ``subject:``.
    """
    import ezc3d  # lazily: only C3D takes need it (start-up)

    frames = np.asarray(take.frames, dtype=np.int64)
    if frames.size > 1 and not (np.diff(frames) == 1).all():
        raise ValueError("C3D needs consecutive frame numbers")
    rate = nominal_rate(take, 30.0)
    pos = np.asarray(take.positions, dtype=np.float64)
    gone = np.isnan(pos).any(axis=2)  # (T, M)
    c = ezc3d.c3d()
    point = c["parameters"]["POINT"]
    point["RATE"]["value"] = [rate]
    point["UNITS"]["value"] = [units or take.units or "mm"]
    point["LABELS"]["value"] = tuple(marker_label(n, subject) for n in take.marker_names)
    pts = np.ones((4, pos.shape[1], pos.shape[0]))
    pts[:3] = np.where(gone[..., None], 0.0, pos).transpose(2, 1, 0)
    c["data"]["points"] = pts
    residuals = np.where(gone.T, -1.0, 0.0)[None]
    c["data"]["meta_points"] = {"residuals": residuals,
                                "camera_masks": np.zeros((7, pos.shape[1], pos.shape[0]), dtype=bool)}
    c["header"]["points"]["first_frame"] = int(frames[0]) if frames.size else 0
    with atomic_path(path) as tmp:
        c.write(str(tmp))


def _sniff(head: bytes) -> bool:
    return len(head) > 1 and head[1] == 0x50 and 2 <= head[0] <= 127 and b"," not in head[:64]


register(Format("c3d", (".c3d",), read_c3d_take, write_c3d_take, _sniff))
