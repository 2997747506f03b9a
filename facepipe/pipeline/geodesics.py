"""Geodesic distances from the handles, started early and run beside the bake's other work.

SciPy's Dijkstra holds the GIL, so a large problem runs on the OpenCL CPU device (a bucket
Dijkstra, :mod:`facepipe.opencl.geodesics`) or in a second process
(:mod:`facepipe.pipeline.background`) while this process factors the shell; the distances are
the same wherever they were computed.
"""

from __future__ import annotations

import os
import tempfile

import numpy as np
import scipy.sparse as sp

from facepipe.core.strain import dijkstra_rows
from facepipe.opencl.geodesics import start as start_on_device
from facepipe.pipeline.background import BackgroundCall


# from this many vertex × source pairs (and 8 sources), the Dijkstra runs start in the background
GEODESICS_IN_A_PROCESS = 2_000_000
# ... on an OpenCL CPU device where there is one (else in a second process)
GEODESICS_ON_DEVICE = True


def geodesic_from(graph: sp.csr_matrix, sources: np.ndarray, limit: float = np.inf) -> np.ndarray:
    """Dijkstra distances along mesh edges from each source vertex.

    Returns
    -------
    (S, V) float64; ``inf`` beyond ``limit`` or in other components.
    """
    return Geodesics(graph, sources, limit).finish()


class Geodesics:
    """Dijkstra from many sources: started on construction, collected by :meth:`finish`.

    SciPy's Dijkstra holds the GIL, so threads would not help, and from every handle over a
    large mesh it is one of the bake's longest steps. A large problem (``background``: by default from
    :data:`GEODESICS_IN_A_PROCESS` pairs on two cores or more) is started at once, to run while
    this process does other work:

    * on an OpenCL CPU device (``device``; by default where there is one,
      :mod:`facepipe.opencl.geodesics`): the same distances to the bit in half the CPU time, on
      the driver's threads;
    * else in a child process that takes the sources first to last, while :meth:`finish`
      takes them from the last down until the two meet, so neither waits for the other however
      busy this process was. The rows are written into one file-backed mapping; a source
      claimed by both at the same instant is computed twice, to the same values. If the child
      fails, its sources are computed here.

    A small problem is computed by :meth:`finish`. ``where`` says which ("opencl", "process",
    "here"). The distances are kept for later calls of :meth:`finish` until :meth:`close`.
    """

    def __init__(self, graph: sp.csr_matrix, sources: np.ndarray, limit: float = np.inf,
                 background: bool | None = None, device: bool | None = None):

        self.graph = graph = sp.csr_matrix(graph)
        self.sources = np.asarray(sources, dtype=np.int64)
        self.n_vertices = graph.shape[0]
        self.child_sources = 0
        self.where = "here"
        if background is None:
            background = len(self.sources) >= 8 and (os.cpu_count() or 1) >= 2 and \
                self.n_vertices * len(self.sources) >= GEODESICS_IN_A_PROCESS
        self._dir = self._child = self._result = self._device = None
        self._closed = False
        self._args = (graph, self.sources, limit)
        if not background:
            return
        if (GEODESICS_ON_DEVICE if device is None else device) and np.isinf(limit):

            self._device = start_on_device(graph, self.sources)
            if self._device is not None:
                self.where = "opencl"
                return
        try:
            self._paths = self._shared_files(len(self.sources), self.n_vertices)
        except OSError:  # no room for the shared rows (the child and this process write them): all here
            return
        self._args = (graph, self.sources, limit) + self._paths
        self._child = BackgroundCall(_claimed_rows, *self._args, 0)
        self.where = "process"

    def _shared_files(self, n_sources: int, n_vertices: int) -> tuple[str, str]:
        """The distance rows and the claims, as files both processes map. The space is allocated now:
        a write into a mapped file that the disk cannot hold would kill the process (SIGBUS)."""

        self._dir = tempfile.TemporaryDirectory(prefix="facepipe-geodesics-")
        try:
            paths = (os.path.join(self._dir.name, "distances.npy"), os.path.join(self._dir.name, "claims.npy"))
            for path, dtype, shape in ((paths[0], np.float64, (n_sources, n_vertices)),
                                       (paths[1], np.uint8, (2, n_sources))):
                np.lib.format.open_memmap(path, mode="w+", dtype=dtype, shape=shape).flush()
                if hasattr(os, "posix_fallocate"):
                    fd = os.open(path, os.O_RDWR)
                    try:
                        os.posix_fallocate(fd, 0, os.fstat(fd).st_size)
                    finally:
                        os.close(fd)
            return paths
        except OSError:
            self._dir.cleanup()
            self._dir = None
            raise

    def finish(self) -> np.ndarray:
        """Compute the sources the child has not reached, wait for it, return the (S, V) distances."""
        if self._result is not None:
            return self._result
        if self._closed:
            raise RuntimeError("the geodesics were closed before they were finished")
        if self._device is not None:
            try:
                self._result = self._device.finish()
            except Exception:  # noqa: BLE001 - the driver failed at run time: the same rows by SciPy
                self.where = "here after the device failed"
            finally:
                self._device.close()
                self._device = None
            if self._result is not None:
                return self._result
        if self._child is None:
            self._result = dijkstra_rows(*self._args[:3])
            return self._result
        try:
            _claimed_rows(*self._args, 1)
            self._child.result()
            claims = np.load(self._paths[1])
            self.child_sources = int((claims[0] & ~claims[1]).sum())
            rows = np.load(self._paths[0], mmap_mode="r")
            # POSIX keeps a mapping valid after its file is removed: no copy of the rows (0.4 GB at
            # 530k vertices); elsewhere they are copied out before the files go
            self._result = rows.view(np.ndarray) if os.name == "posix" else np.array(rows)
        finally:
            self._stop()
        return self._result

    def close(self) -> None:
        """Stop the child if it still runs (an error, or the result not wanted), remove the files and
        let go of the distances."""
        self._stop()
        self._result = None
        self._closed = True

    def _stop(self) -> None:
        if self._device is not None:
            self._device.close()
            self._device = None
        if self._child is not None:
            self._child.cancel()
            self._dir.cleanup()


def _claimed_rows(graph, sources, limit, distances_path, claims_path, side: int) -> int:
    """Dijkstra rows of the sources not claimed by the other side: side 0 from the first source up,
    side 1 from the last down, each stopping where the other has been. Returns the rows computed."""
    distances = np.load(distances_path, mmap_mode="r+")
    claims = np.load(claims_path, mmap_mode="r+")
    order = range(len(sources)) if side == 0 else range(len(sources) - 1, -1, -1)
    done = 0
    for i in order:
        if claims[1 - side, i]:
            break
        claims[side, i] = 1
        distances[i] = dijkstra_rows(graph, sources[i:i + 1], limit)[0]
        done += 1
    # no flush: both processes share the mapping's pages, and the file is removed before the
    # kernel would write them back, so the rows never go to the disk
    return done
