"""Reading the ``.npz`` archives users hand over (models, fits, truths) with a message that says what
the file should have been.

NumPy reads anything that is not a zip or ``.npy`` file as a pickle, and with
``allow_pickle=False`` refuses it with advice to load it unsafely — advice no facepipe user should
follow (a text file given by mistake is no pickle, and a pickle from elsewhere can run code). So a
file is checked for the zip signature first, and nothing is ever unpickled.
"""

from __future__ import annotations

import zipfile
from pathlib import Path

import numpy as np

from facepipe.errors import InputError

_NPY_MAGIC = b"\x93NUMPY"


def describe_start(path: Path) -> str:
    """A few words on what a file that is not an archive looks like: text (its first line) or binary."""
    with open(path, "rb") as fh:
        head = fh.read(256)
    if not head:
        return "it is empty"
    if head.startswith(_NPY_MAGIC):
        return "it is a single .npy array, not an .npz archive"
    try:
        first = head.decode("utf-8").splitlines()[0].strip()
    except (UnicodeDecodeError, IndexError):
        return "it is a binary file of another kind"
    return f"it is a text file (first line: {first[:60]!r})"


def open_npz(path, expected: str, hint: str | None = None):
    """``np.load`` of an ``.npz`` archive (``allow_pickle=False``), for reading arrays by name.

    Parameters
    ----------
    path : the file.
    expected : what it should be, for the message (e.g. "a model written by 'facepipe bake'").
    hint : the fix, for the message.

    Returns
    -------
    numpy.lib.npyio.NpzFile (close it, or use it as a context manager).

    Raises
    ------
    InputError
        A missing file, or one that is not a zip archive (saying what it looks like and what it
        should be), or an archive NumPy cannot open.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError("file not found" if not path.exists() else "this is a folder, not a file", path=path,
                         hint=hint)
    if not zipfile.is_zipfile(path):
        raise InputError(f"not an .npz archive: {describe_start(path)}; expected {expected}", path=path, hint=hint)
    try:
        return np.load(path, allow_pickle=False)
    except Exception as exc:  # a damaged or truncated archive
        raise InputError(f"cannot read this .npz archive ({exc.__class__.__name__}: {exc}); expected {expected}",
                         path=path, hint=hint) from None


TRUTH_EXPECTED = "a truth .npz with 'positions' (frames × vertices × 3) and optionally 'frame' (the take's frame numbers)"


def read_truth_extras(path, n_frames: int) -> dict:
    """What else a truth file of ``n_frames`` frames says of them, where it says it: ``time`` (F,)
    seconds, and the head's pose ``rotation`` (F, 3, 3) and ``translation`` (F, 3) (world = R ·
    head + t).

    Raises
    ------
    InputError
        A member of the wrong shape.
    """
    out = {}
    n = int(n_frames)
    with open_npz(path, TRUTH_EXPECTED) as data:
        for name, tail in (("time", ()), ("rotation", (3, 3)), ("translation", (3,))):
            if name in data.files:
                value = np.asarray(data[name], dtype=np.float64)
                if value.shape != (n,) + tail:
                    raise InputError(f"the truth's '{name}' has shape {value.shape}, expected {(n,) + tail}", path=path)
                out[name] = value
    return out


def read_truth(path) -> tuple[np.ndarray, np.ndarray]:
    """A truth file's positions (F, V, 3) and frame numbers (F,) (0, 1, … when it has none).

    Raises
    ------
    InputError
        Not an archive (see :func:`open_npz`), no ``positions``, or arrays of the wrong shape.
    """
    with open_npz(path, TRUTH_EXPECTED) as data:
        if "positions" not in data.files:
            raise InputError(f"the archive has no 'positions' (it holds {', '.join(data.files) or 'nothing'}); "
                             f"expected {TRUTH_EXPECTED}", path=path)
        try:
            positions = data["positions"]
            frames = np.asarray(data["frame"]) if "frame" in data.files else np.arange(positions.shape[0])
        except Exception as exc:  # a damaged member, or one holding objects
            raise InputError(f"cannot read the truth ({exc.__class__.__name__}: {exc})", path=path) from None
    if positions.ndim != 3 or positions.shape[2] != 3 or frames.shape != (positions.shape[0],):
        raise InputError(f"truth positions have shape {positions.shape} and frames {frames.shape}; expected "
                         f"{TRUTH_EXPECTED}", path=path)
    return positions, frames
