"""Reading the ``.npz`` archives users hand over (models, fits, truths) with a message that says what
the file should have been; writing large ones while their arrays are still being computed
(:class:`NpzWriter`).

NumPy reads anything that is not a zip or ``.npy`` file as a pickle, and with
``allow_pickle=False`` refuses it with advice to load it unsafely — advice no facepipe user should
follow (a text file given by mistake is no pickle, and a pickle from elsewhere can run code). So a
file is checked for the zip signature first, and nothing is ever unpickled.
"""

from __future__ import annotations

import zipfile
import zlib
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

from facepipe.errors import InputError
from facepipe.io.atomic import atomic_path

_NPY_MAGIC = b"\x93NUMPY"
_ZIP_MAGIC = b"PK\x03\x04"

#: What reading an opened archive's members raises where one is damaged (a bad CRC, a member cut
#: short) or is not what was expected (a missing key, the wrong dtype): catch these around the reads.
NPZ_READ_ERRORS = (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile, zlib.error)


def describe_start(path: Path) -> str:
    """A few words on what a file that is not an archive looks like: text (its first line) or binary."""
    with open(path, "rb") as fh:
        head = fh.read(256)
    if not head:
        return "it is empty"
    if head.startswith(_NPY_MAGIC):
        return "it is a single .npy array, not an .npz archive"
    if head.startswith(_ZIP_MAGIC):
        return "it starts as one but is cut short or damaged (an interrupted copy or write?)"
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


class NpzWriter:
    """An ``.npz`` archive written atomically, array by array, by a background thread.

    Arrays are handed over with :meth:`add` as soon as they are known and written while the
    caller goes on computing the others: a bake knows its mesh and shell basis (two thirds of a
    model file) seconds before its detail weights. Leaving the ``with`` block normally waits for
    the writes, finishes the archive and renames it into place; leaving it by an exception
    removes the temporary file, so nothing half-written ever has the final name. The archive
    is what ``np.savez`` writes (uncompressed, zip64), its members in the order they were added.

    Example
    -------
    >>> with NpzWriter("out.npz") as npz:   # doctest: +SKIP
    ...     npz.add("rest", rest, np.float32)
    ...     npz.add("weights", solve(...))
    """

    def __init__(self, path):
        self.path = Path(path)
        self._atomic = atomic_path(path)
        tmp = self._atomic.__enter__()
        try:
            self._zip = zipfile.ZipFile(tmp, "w", zipfile.ZIP_STORED, allowZip64=True)
        except BaseException as exc:
            self._atomic.__exit__(type(exc), exc, exc.__traceback__)
            raise
        self._pool = ThreadPoolExecutor(1, thread_name_prefix="npz-writer")
        self._writes = []
        self._names: set[str] = set()

    def __contains__(self, name: str) -> bool:
        return name in self._names

    def add(self, name: str, array, dtype=None) -> None:
        """Write ``array`` (cast to ``dtype``, if given) as member ``name``, in the background: it
        is read when its turn comes, so it must not be changed after it is handed over."""
        if name in self._names:
            raise ValueError(f"{name!r} is already in the archive")
        self._names.add(name)
        self._writes.append(self._pool.submit(self._write, name, array, dtype))

    #: Arrays to be cast or laid out anew above this many bytes are converted a chunk at a time.
    CHUNKED_BYTES = 32 << 20

    def _write(self, name: str, array, dtype) -> None:
        array = np.asarray(array)
        target = array.dtype if dtype is None else np.dtype(dtype)
        with self._zip.open(name + ".npy", "w", force_zip64=True) as member:
            if (array.dtype == target and array.flags.c_contiguous) or array.dtype.hasobject \
                    or array.size * target.itemsize <= self.CHUNKED_BYTES:
                # (the cast, too, off the caller's thread)
                np.lib.format.write_array(member, np.ascontiguousarray(array, dtype=target), allow_pickle=False)
            else:
                _write_cast(member, array, target)

    def __enter__(self) -> "NpzWriter":
        return self

    def __exit__(self, exc_type, exc, tb) -> bool:
        if exc_type is not None:
            self._abandon(exc)
            return False
        try:
            for write in self._writes:
                write.result()  # a write's error (a full disk) is raised here
            self._zip.close()
        except BaseException as error:
            self._abandon(error)
            raise
        self._pool.shutdown()
        self._atomic.__exit__(None, None, None)  # the rename
        return False

    def _abandon(self, error: BaseException) -> None:
        """Stop writing and remove the temporary file (raising the disk-full error that names the
        folder, where that was the trouble)."""
        for write in self._writes:
            write.cancel()
        self._pool.shutdown(wait=True)  # a write under way ends before its file is removed
        try:
            self._zip.close()
        except Exception:  # noqa: BLE001 - the file goes anyway; the first error is the one told
            pass
        self._atomic.__exit__(type(error), error, error.__traceback__)


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


def _write_cast(member, array: np.ndarray, dtype: np.dtype) -> None:
    """``array`` cast to ``dtype`` and laid out in C order, as an .npy member: the bytes that
    ``write_array`` writes of ``np.ascontiguousarray(array, dtype)``, cast 16 MB at a time
    without that whole copy (a model's float32 shell basis is 0.19 GB at 530k vertices, and
    every fresh page costs the kernel its zeroing)."""
    header = np.lib.format.header_data_from_array_1_0(np.empty(array.shape, dtype))  # (never touched)
    try:
        np.lib.format.write_array_header_1_0(member, header)
    except ValueError:  # a header too long for format 1.0, as write_array goes on to 2.0
        np.lib.format.write_array_header_2_0(member, header)
    for chunk in np.nditer(array, flags=["external_loop", "buffered", "zerosize_ok"], op_dtypes=[dtype],
                           casting="unsafe", buffersize=max((16 << 20) // dtype.itemsize, 1), order="C"):
        member.write(chunk.tobytes("C"))
