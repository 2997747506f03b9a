"""Which Dask cluster a batch runs on: an existing scheduler, or a LocalCluster sized to this machine.

An existing cluster is named by ``--scheduler tcp://HOST:8786``, ``--scheduler-file F`` (what
``dask scheduler --scheduler-file F`` writes, handy on shared file systems and job queues) or the
``DASK_SCHEDULER_ADDRESS`` environment variable, in that order. Without one, a LocalCluster of
worker processes (one task thread each: a take's array work has its own threads, see
:mod:`facepipe.parallel`) with the machine's memory shared among them.
"""

from __future__ import annotations

import contextlib
import os
from dataclasses import dataclass

import dask
from distributed import Client, LocalCluster

from facepipe import parallel

SCHEDULER_ENV = "DASK_SCHEDULER_ADDRESS"

#: Settings of the local cluster that a batch owns. Dask's defaults watch a cluster closely: a
#: statistical profiler samples every worker's stacks every 10 ms, event loops tick every 20 ms,
#: nannies poll memory every 100 ms; an idle 2-worker cluster then takes ~9 % of a core (measured),
#: taken from the takes on a small machine. A take is seconds of array work with its own timings
#: (replay.json), so these are relaxed (~1.4 % idle); work stealing is off: takes wait on the
#: scheduler (queuing) and go to whichever worker is free, there is nothing to steal.
LOCAL_CONFIG = {
    "distributed.worker.profile.enabled": False,
    "distributed.admin.tick.interval": "1s",
    "distributed.admin.system-monitor.interval": "2s",
    "distributed.worker.memory.monitor-interval": "1s",
    "distributed.scheduler.work-stealing": False,
}


class ClusterError(RuntimeError):
    """The cluster could not be reached or was lost (exit status 1)."""


@dataclass(frozen=True)
class ClusterSpec:
    workers: int | None = None  # LocalCluster size (default: the CPUs this process may use)
    scheduler: str | None = None
    scheduler_file: str | None = None
    connect_timeout: float = 30.0
    # a take whose worker dies is run again elsewhere up to this many times (LocalCluster; an
    # existing scheduler applies its own distributed.scheduler.allowed-failures)
    allowed_failures: int = 3

    def describe(self) -> str:
        if self.scheduler_file:
            return f"scheduler file {self.scheduler_file}"
        address = self.scheduler or os.environ.get(SCHEDULER_ENV)
        return f"scheduler {address}" if address else f"local cluster of {self.local_workers()} workers"

    def local_workers(self) -> int:
        return int(self.workers) if self.workers else parallel.available_cpus()


@contextlib.contextmanager
def open_client(spec: ClusterSpec):
    """A connected ``distributed.Client`` (and the LocalCluster it owns, closed on exit)."""
    address = spec.scheduler or os.environ.get(SCHEDULER_ENV)
    cluster = None
    try:
        if spec.scheduler_file:
            client = Client(scheduler_file=spec.scheduler_file, timeout=spec.connect_timeout)
        elif address:
            client = Client(address, timeout=spec.connect_timeout)
        else:
            with dask.config.set({**LOCAL_CONFIG, "distributed.scheduler.allowed-failures": spec.allowed_failures}):
                # memory_limit "auto": the machine's memory shared evenly among the workers
                cluster = LocalCluster(n_workers=spec.local_workers(), threads_per_worker=1, processes=True,
                                       memory_limit="auto", dashboard_address=":0")  # any free port
            client = Client(cluster, timeout=spec.connect_timeout)
    except (OSError, TimeoutError) as exc:
        if cluster is not None:
            cluster.close()
        raise ClusterError(f"cannot reach the cluster ({spec.describe()}): {exc}") from None
    try:
        yield client
    finally:
        with contextlib.suppress(Exception):
            client.close()
        if cluster is not None:
            with contextlib.suppress(Exception):
                cluster.close()


def slots_by_host(client) -> dict[str, int]:
    """Task slots (worker threads) per host: how many takes may run side by side on each."""
    slots: dict[str, int] = {}
    for info in client.scheduler_info().get("workers", {}).values():
        host = info.get("host")
        slots[host] = slots.get(host, 0) + int(info.get("nthreads", 1))
    return slots
