"""Atomic output: write to a temporary name beside the target, then rename.

An interrupted run never leaves a half-written file under the final name.
"""

from __future__ import annotations

import contextlib
import os
import secrets
from pathlib import Path

from facepipe.errors import DISK_FULL


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike):
    """Yield a temporary path in the target's folder; rename it to ``path`` on success.

    Example
    -------
    >>> with atomic_path("out.npz") as tmp:   # doctest: +SKIP
    ...     np.savez(tmp, a=1)
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = None
    try:
        # the name is known before the file exists, so an interrupt (Ctrl-C, SIGTERM) at any point
        # after this, creation included, finds it to remove; the mode is the usual one (umask applied)
        while True:
            tmp = str(path.parent / f".{path.name}.{secrets.token_hex(6)}.part{path.suffix}")
            try:
                os.close(os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666))
                break
            except FileExistsError:  # another run's temporary file: not ours to remove
                tmp = None
        yield Path(tmp)
        os.replace(tmp, path)
    except BaseException as exc:
        if tmp is not None:
            with contextlib.suppress(OSError):  # not made, or already gone
                os.unlink(tmp)
        if isinstance(exc, OSError) and exc.filename is None and exc.errno in DISK_FULL:
            # a write that ran out of room says where (os.write names no file)
            raise OSError(exc.errno, exc.strerror, str(path.parent)) from exc
        raise


@contextlib.contextmanager
def atomic_open(path: str | os.PathLike, mode: str = "w", **kwargs):
    """Open a temporary file for writing; it replaces ``path`` only when the block succeeds."""
    with atomic_path(path) as tmp:
        with open(tmp, mode, **kwargs) as fh:
            yield fh
