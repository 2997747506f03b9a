"""SIGTERM handled as Ctrl-C: a terminated command unwinds like an interrupted one.

Outputs are written under temporary names and renamed when complete
(:mod:`facepipe.io.atomic`); the temporary file is removed when the block that writes it is left
by an exception. Python turns SIGINT into KeyboardInterrupt, but SIGTERM (``kill``, a job
scheduler's time limit, a closing terminal's session manager) ends the process at once, leaving
the hidden ``.part`` files behind. Here SIGTERM raises :class:`Terminated`, a KeyboardInterrupt,
in the main thread, so the same clean-up runs.
"""

from __future__ import annotations

import contextlib
import signal
import threading


class Terminated(KeyboardInterrupt):
    """Raised in the main thread when the process receives SIGTERM."""

    exit_status = 128 + signal.SIGTERM


def _raise_terminated(signum, frame):
    raise Terminated()


@contextlib.contextmanager
def terminate_as_interrupt():
    """Within the block, SIGTERM raises :class:`Terminated` (the previous handler is restored
    after it). Only the main thread may install signal handlers: elsewhere (a command run from a
    library's worker thread) this does nothing."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGTERM, _raise_terminated)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)
