"""One attempt at a time in a take's output folder, across processes and hosts.

Dask may run a task more than once at the same time: a worker the scheduler gave up on (lost
heartbeat, network partition, a nanny that lost its worker's connection) can still be running
its take when the take is run again elsewhere, and a batch started while an earlier one's
attempt still runs writes to the same folder. Every attempt writes its files to temporary names
of its own, but an attempt that starts by removing what killed attempts left half-written would
remove a live attempt's files too, and two attempts finishing in either order could leave one's
``positions.npy`` beside the other's ``batch_take.json``.

So an attempt holds an exclusive ``flock`` on ``OUT/<take>/.batch.lock`` from before it touches
the folder until its stamp is written. The kernel drops the lock when the holder's process dies
(SIGKILL included), so a killed attempt never blocks the next one, and whatever temporary files
are in the folder once the lock is held are a dead attempt's. ``flock`` works between hosts on
NFSv4 and most cluster file systems (Lustre mounted with ``-o flock``); where ``fcntl`` does not
exist (native Windows) attempts are not serialised.
"""

from __future__ import annotations

import contextlib
import os
from pathlib import Path

try:
    import fcntl
except ImportError:  # native Windows
    fcntl = None

LOCK_NAME = ".batch.lock"


@contextlib.contextmanager
def take_lock(out_dir: Path):
    """Hold the take folder's lock for the block (waiting while another attempt holds it)."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    fd = os.open(out_dir / LOCK_NAME, os.O_RDWR | os.O_CREAT, 0o666)
    try:
        if fcntl is not None:
            fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        os.close(fd)  # releases the lock
