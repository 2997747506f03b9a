"""Output paths checked before any work: every command that writes calls :func:`check_output_path`
first, so a destination that cannot be written (a parent that is a file, a folder without write
permission) stops the command at once with exit status 2, not with a traceback after minutes of
fitting or replaying.

A replay folder is also guarded against being replayed into again by mistake:
:func:`prepare_replay_folder` refuses a folder holding an earlier replay unless forced, and then
removes the earlier replay's results that the new one would not replace (an ``eval.json`` beside
new positions would describe the old ones).
"""

from __future__ import annotations

import contextlib
import os
import shutil
from pathlib import Path

from facepipe.errors import InputError

#: Files an earlier ``facepipe replay`` (or the commands run on its folder) may have left in it;
#: a forced replay removes every one it does not write again itself.
REPLAY_RESULTS = ("positions.npy", "large_scale.npy", "handles.npz", "video.npz", "replay.json", "eval.json",
                  "compare.json", "compare.png", "preview.png", "preview.mp4", "preview.gif")


def check_output_path(path, kind: str = "file", what: str = "output") -> Path:
    """Check that ``path`` can be written, before any work: InputError (exit 2) naming it if not.

    Parameters
    ----------
    path : the file or folder a command will write (need not exist).
    kind : "file" (an existing folder there is an error), "folder" (an existing file there is an
        error) or "either" (a file, or a folder to write into: single-file exports).
    what : what the path is for, in the message ("output", "export destination", …).

    Returns
    -------
    Path, as given.

    Raises
    ------
    InputError
        A parent that is a file; ``path`` of the wrong kind; the nearest existing folder (the one
        the missing parents would be made in) or ``path`` itself not writable.
    """
    if kind not in ("file", "folder", "either"):
        raise ValueError(f"unknown kind {kind!r}")
    path = Path(path)
    if path.exists():
        if kind == "file" and path.is_dir():
            raise InputError(f"the {what} is a folder, expected a file name", path=path,
                             hint="give a file name (e.g. inside that folder)")
        if kind == "folder" and not path.is_dir():
            raise InputError(f"the {what} is a file, not a folder", path=path,
                             hint="give a folder name (it is made if missing)")
        writable_dir = path if path.is_dir() else path.parent
        if path.is_dir() and not os.access(path, os.W_OK | os.X_OK):
            raise InputError(f"cannot write into the {what} folder (no permission)", path=path,
                             hint="choose a folder you can write to")
        if not path.is_dir() and not os.access(writable_dir, os.W_OK | os.X_OK):
            raise InputError(f"cannot replace the {what}: its folder is not writable", path=path,
                             hint="choose a folder you can write to")
        return path
    parent = path.absolute().parent
    while not parent.exists():
        parent = parent.parent
    if not parent.is_dir():
        raise InputError(f"cannot write the {what}: {parent} is a file, not a folder", path=path,
                         hint="choose a path whose folders are folders")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise InputError(f"cannot write the {what}: the folder {parent} is not writable (no permission)", path=path,
                         hint="choose a folder you can write to")
    return path


def prepare_replay_folder(path, force: bool) -> Path:
    """Check a replay's output folder (as :func:`check_output_path`) and that it holds no earlier
    replay: InputError without ``force``; with it the earlier replay's results are removed (before
    any work, so a folder never mixes two replays' files)."""
    path = check_output_path(path, kind="folder", what="replay folder")
    earlier = [path / name for name in REPLAY_RESULTS if (path / name).exists()]
    if not earlier:
        return path
    if not force:
        raise InputError(f"this folder holds an earlier replay ({', '.join(p.name for p in earlier)})", path=path,
                         hint="pass --force to replace it (its results are removed), or replay into another folder")
    for p in earlier:
        if p.is_dir():
            shutil.rmtree(p)
        else:
            with contextlib.suppress(FileNotFoundError):
                p.unlink()
    return path
