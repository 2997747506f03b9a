"""Edits over a take: handle offsets keyed at frames and eased in and out.

An edit is a layer over the take, not a change of it: for every frame the handles' head-space
positions become ``head + offsets(frame)`` before the shell, so the wrinkles follow the edited
handles like any other motion. An edit moves one or more handles by fixed offsets with full
weight at its key frame; the weight eases from 0 to 1 over ``ease_in`` frames before the key and
back to 0 over ``ease_out`` frames after it (smoothstep 3x² − 2x³: no jump in position or
velocity where an edit starts or ends). The offsets of overlapping edits add.

Frame numbers are the take's own (the ``frame`` column), so an edit keeps its place whatever
part of the take is replayed. The editor page and ``replay --edits`` both call :func:`edit_offsets`:
the page's server evaluates exactly what a batch replay does.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class HandleEdit:
    """Offsets of some handles at a key frame, eased in and out.

    Attributes
    ----------
    frame : key frame number (the take's numbering), where the weight is 1.
    offsets : handle index → (3,) offset in the rig's units, head space.
    ease_in, ease_out : frames over which the weight rises before / falls after the key
        (0 = a step at the key frame on that side).
    """

    frame: float
    offsets: dict[int, tuple[float, float, float]]
    ease_in: float = 0.0
    ease_out: float = 0.0


def smoothstep(x: np.ndarray) -> np.ndarray:
    """3x² − 2x³ on [0, 1], clamped outside: zero slope at both ends."""
    x = np.clip(np.asarray(x, dtype=np.float64), 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


def edit_weight(edit: HandleEdit, frames: np.ndarray) -> np.ndarray:
    """The edit's weight at each frame number: 1 at the key, eased to 0 over ease_in / ease_out."""
    frames = np.asarray(frames, dtype=np.float64)
    before = frames < edit.frame
    after = frames > edit.frame
    weight = np.ones_like(frames)
    if edit.ease_in > 0:
        weight[before] = smoothstep(1.0 - (edit.frame - frames[before]) / edit.ease_in)
    else:
        weight[before] = 0.0
    if edit.ease_out > 0:
        weight[after] = smoothstep(1.0 - (frames[after] - edit.frame) / edit.ease_out)
    else:
        weight[after] = 0.0
    return weight


def edit_offsets(edits: list[HandleEdit], frames: np.ndarray, n_handles: int) -> np.ndarray:
    """Summed offsets of all edits, (T, H, 3), at the given frame numbers (T,)."""
    frames = np.asarray(frames, dtype=np.float64).reshape(-1)
    out = np.zeros((len(frames), n_handles, 3))
    for edit in edits:
        weight = edit_weight(edit, frames)
        if not weight.any():
            continue
        for handle, offset in edit.offsets.items():
            out[:, handle, :] += weight[:, None] * np.asarray(offset, dtype=np.float64)
    return out


def apply_edits(head: np.ndarray, frames: np.ndarray, edits: list[HandleEdit]) -> np.ndarray:
    """Head-space handle positions (T, H, 3) with the edits' offsets added (a new array)."""
    if not edits:
        return head
    offsets = edit_offsets(edits, frames, head.shape[1])
    return (head.astype(np.float64) + offsets).astype(head.dtype, copy=False)
