"""How many threads facepipe's own array work runs on, decided in one place.

Blocks of vertices, poses or file rows are independent and NumPy releases the GIL inside its
array loops and LAPACK calls, so a few threads share the work. The count respects the user's
limits: ``FACEPIPE_THREADS``, else ``OMP_NUM_THREADS`` (the limit most schedulers and users set
for numeric code), else the CPUs this process may run on (its affinity, which batch schedulers
and containers narrow), else ``os.cpu_count()``. A program that runs several facepipe jobs side
by side (batch workers) sets its share with :func:`set_thread_count`.

Every block sees the same arithmetic on any number of threads, so results do not depend on
the count.
"""

from __future__ import annotations

import os
import threading
from collections import deque
from concurrent.futures import ThreadPoolExecutor, wait
from contextlib import contextmanager
from typing import Callable, Iterable, Iterator, TypeVar

from threadpoolctl import threadpool_limits

T = TypeVar("T")
R = TypeVar("R")

THREADS_ENV = "FACEPIPE_THREADS"

_lock = threading.Lock()
_override: int | None = None
_executor: ThreadPoolExecutor | None = None
_executor_size = 0
_in_worker = threading.local()


def available_cpus() -> int:
    """CPUs this process may run on: its affinity where the OS has one, else all of them."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not on Linux
        return max(1, os.cpu_count() or 1)


def _count_from_env(name: str) -> int | None:
    """A positive thread count from an environment variable, or None when unset or unusable.

    OMP_NUM_THREADS may list one count per nesting level ("4,2"): the outer one applies."""
    value = os.environ.get(name, "").split(",")[0].strip()
    try:
        count = int(value)
    except ValueError:
        return None
    return count if count >= 1 else None


def thread_count() -> int:
    """Threads for facepipe's block-parallel work (at least 1).

    :func:`set_thread_count`, else ``FACEPIPE_THREADS``, else ``OMP_NUM_THREADS``, else the
    process's CPU affinity."""
    if _override is not None:
        return _override
    for name in (THREADS_ENV, "OMP_NUM_THREADS"):
        count = _count_from_env(name)
        if count is not None:
            return count
    return available_cpus()


def set_thread_count(count: int | None) -> None:
    """Use ``count`` threads from now on (None: back to the environment and affinity)."""
    global _override
    if count is not None and int(count) < 1:
        raise ValueError(f"thread count must be at least 1, got {count}")
    with _lock:
        _override = None if count is None else int(count)


def _mark_worker() -> None:
    _in_worker.active = True


def _shared_executor(size: int) -> ThreadPoolExecutor:
    """The process's executor of ``size`` threads, created on first use (and again when the
    count changes; the old one finishes what it has and lets its threads go)."""
    global _executor, _executor_size
    with _lock:
        if _executor is None or _executor_size != size:
            if _executor is not None:
                _executor.shutdown(wait=False)
            _executor = ThreadPoolExecutor(size, thread_name_prefix="facepipe-block", initializer=_mark_worker)
            _executor_size = size
        return _executor


def _forget_executor() -> None:
    # a forked child has none of its parent's threads: it starts its own executor when it needs one
    global _executor, _executor_size
    _executor, _executor_size = None, 0


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_forget_executor)


def map_blocks(function: Callable[[T], R], items: Iterable[T]) -> list[R]:
    """``[function(item) for item in items]``, on up to :func:`thread_count` threads.

    Results come in the order of ``items``; where calls raise, the first item's exception (in
    that order) is raised, after the calls not yet started are cancelled and the running ones
    have finished (none is still writing when this returns). One thread, a single item, or a
    call from inside one of the workers (nested blocks) runs the items here, in order.
    """
    items = list(items)
    threads = thread_count()
    if min(len(items), threads) <= 1 or getattr(_in_worker, "active", False):
        return [function(item) for item in items]
    executor = _shared_executor(threads)
    futures = [executor.submit(function, item) for item in items]
    try:
        return [future.result() for future in futures]
    except BaseException:
        for future in futures:
            future.cancel()
        wait(futures)
        raise


#: What the calls under way of :func:`map_in_order` may hold together where the caller says how
#: much one holds (``item_bytes``): a machine of many threads does not keep as many 2K maps in memory
ORDERED_MEMORY = 1 << 30


def map_in_order(function: Callable[[T], R], items: Iterable[T], ahead: int | None = None,
                 item_bytes: int | None = None) -> Iterator[R]:
    """``function(item)`` for each item, yielded in the order of ``items`` as each is ready, on up
    to :func:`thread_count` threads with at most ``ahead`` calls under way (default: twice the
    threads; with ``item_bytes``, the memory one call holds, no more than fit in
    :data:`ORDERED_MEMORY`): for a long stream whose results are consumed one by one (a movie's
    frames), the memory of a few results, not of all.

    A call that raises raises here when its turn comes, after the calls under way have finished
    (those not started are cancelled); so does closing the generator early (a consumer that
    stops). One thread, or a call from inside one of the workers, runs the items here, in order.
    """
    threads = thread_count()
    if threads <= 1 or getattr(_in_worker, "active", False):
        for item in items:
            yield function(item)
        return
    executor = _shared_executor(threads)
    ahead = 2 * threads if ahead is None else int(ahead)
    if item_bytes:
        ahead = min(ahead, ORDERED_MEMORY // max(1, int(item_bytes)))
    ahead = max(1, ahead)
    pending = deque()
    try:
        for item in items:
            pending.append(executor.submit(function, item))
            if len(pending) >= ahead:
                yield pending.popleft().result()
        while pending:
            yield pending.popleft().result()
    finally:
        for future in pending:
            future.cancel()
        wait(pending)


@contextmanager
def serial_blas():
    """BLAS and LAPACK on one thread of their own within the block, while :func:`map_blocks` shares
    batched small-matrix work (thousands of per-vertex SVDs and solves) among facepipe's threads.

    OpenBLAS splits even a 50 × 50 SVD over its threads; called from several threads at once, on
    a busy machine, a batch then took 20× longer than on one thread each. The limit is the
    library's, process-wide, for the duration of the block."""
    with threadpool_limits(limits=1, user_api="blas"):
        yield
