"""The editor's layer of edits with undo and redo.

A drag adds an offset of one handle at the current frame: into the edit already keyed at that
frame with the same easing (so a handle dragged twice at a frame has one offset), else as a new
edit. Every change pushes the previous list on the undo stack and clears the redo stack.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from facepipe.core.edits import HandleEdit
from facepipe.io.edits_file import edits_to_data, write_edits


class EditHistory:
    """The current edits and the lists that undo and redo restore (edits are immutable values)."""

    def __init__(self, edits: list[HandleEdit] | None = None):
        self.edits: list[HandleEdit] = list(edits or [])
        self._undo: list[list[HandleEdit]] = []
        self._redo: list[list[HandleEdit]] = []

    @property
    def can_undo(self) -> bool:
        return bool(self._undo)

    @property
    def can_redo(self) -> bool:
        return bool(self._redo)

    def _change(self, edits: list[HandleEdit]) -> None:
        self._undo.append(self.edits)
        self._redo.clear()
        self.edits = edits

    def add_offset(self, frame: float, handle: int, offset, ease_in: float, ease_out: float) -> None:
        """Move ``handle`` by ``offset`` at key ``frame`` (merged into that frame's edit with these eases)."""
        offset = tuple(float(v) for v in offset)
        edits = list(self.edits)
        for k, edit in enumerate(edits):
            if edit.frame == frame and edit.ease_in == ease_in and edit.ease_out == ease_out:
                offsets = dict(edit.offsets)
                before = np.asarray(offsets.get(handle, (0.0, 0.0, 0.0)))
                offsets[handle] = tuple(float(v) for v in before + np.asarray(offset))
                edits[k] = HandleEdit(frame, offsets, ease_in, ease_out)
                break
        else:
            edits.append(HandleEdit(float(frame), {handle: offset}, float(ease_in), float(ease_out)))
        self._change(edits)

    def clear(self) -> None:
        if self.edits:
            self._change([])

    def undo(self) -> bool:
        if not self._undo:
            return False
        self._redo.append(self.edits)
        self.edits = self._undo.pop()
        return True

    def redo(self) -> bool:
        if not self._redo:
            return False
        self._undo.append(self.edits)
        self.edits = self._redo.pop()
        return True

    def state(self, handle_names: list[str], units: str | None) -> dict:
        """The JSON the page shows: the edits (as in EDITS.json) and whether undo / redo can act."""
        return {"edits": edits_to_data(self.edits, handle_names, units)["edits"],
                "can_undo": self.can_undo, "can_redo": self.can_redo}

    def save(self, path: Path, handle_names: list[str], units: str | None) -> None:
        write_edits(path, self.edits, handle_names, units)
