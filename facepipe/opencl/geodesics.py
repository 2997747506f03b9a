"""Geodesic distances from many sources on an OpenCL CPU device (``geodesics.cl``).

The bake needs Dijkstra from every handle over the whole mesh (the WPSD weights), and
SciPy's heap Dijkstra holds the GIL. The kernel runs the bucket form (see ``geodesics.cl``),
bit-identical to it and cheaper in CPU time (``make bench`` times the bake's phases), on
the OpenCL CPU driver that ships with facepipe (PoCL); it is queued at once and runs on the
driver's threads while Python goes on loading and factoring. It is a CPU kernel (one source
per work-item, a sequential walk), so a CPU device is chosen whatever ``--device`` says for
replay. :func:`start` returns None where it cannot help (no CPU device or no double
precision, limited searches, edge lengths too uneven for buckets); the caller then uses SciPy.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from facepipe.opencl.device import build_program
from facepipe.opencl.device import list_devices
from facepipe.opencl.device import device_context

# the ring of buckets grows as longest / shortest edge; past this, a heap is the better queue
MAX_RING = 1 << 13


def _cpu_device():
    """A CPU OpenCL device with double precision (PoCL's first), or None."""
    try:
        import pyopencl as cl  # lazily: facepipe runs without an OpenCL driver


        cpus = [dev for _, _, dev in list_devices() if dev.type & cl.device_type.CPU and dev.double_fp_config]
    except Exception:  # noqa: BLE001 - no pyopencl, no ICD loader, a broken driver: SciPy instead
        return None
    pocl = [dev for dev in cpus if "portable computing language" in dev.platform.name.lower()]
    return (pocl or cpus or [None])[0]


def ring_size(weights: np.ndarray) -> tuple[int, float] | None:
    """(buckets in the ring, bucket width) for edge lengths ``weights``, or None where the
    spread of lengths is too wide (or a length is not positive and finite)."""
    if weights.size == 0:
        return None
    shortest, longest = float(weights.min()), float(weights.max())
    if not (shortest > 0 and np.isfinite(longest)):
        return None
    delta = shortest * (1.0 - 1e-9)  # at most the shortest edge, after rounding
    need = int(np.floor(longest / delta)) + 2
    ring = 1 << max(need - 1, 1).bit_length()
    return (ring, delta) if ring <= MAX_RING else None


class DeviceGeodesics:
    """Distances (S, V) float64 from ``sources`` over the symmetric ``graph``, computed on the
    device from construction on; :meth:`finish` waits and returns them."""

    def __init__(self, graph: sp.csr_matrix, sources: np.ndarray, device, ring: int, delta: float):
        import pyopencl as cl  # lazily: facepipe runs without an OpenCL driver


        self.device = device
        context = device_context(device)
        self._queue = cl.CommandQueue(context, device)
        program = build_program(context, {"RING": ring}, "geodesics.cl")
        n = graph.shape[0]
        S = len(sources)
        items = max(1, min(device.max_compute_units, S))
        mf = cl.mem_flags

        def upload(a):
            return cl.Buffer(context, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=np.ascontiguousarray(a))

        # the distances go straight into this array (a CPU device works in host memory)
        self._out = np.empty((S, n), dtype=np.float64)
        self._buffers = [upload(graph.indptr.astype(np.int32)), upload(graph.indices.astype(np.int32)),
                         upload(graph.data.astype(np.float64)), upload(np.asarray(sources, dtype=np.int32)),
                         cl.Buffer(context, mf.READ_WRITE | mf.COPY_HOST_PTR, hostbuf=np.zeros(1, np.int32)),
                         cl.Buffer(context, mf.READ_WRITE | mf.USE_HOST_PTR, hostbuf=self._out)]
        scratch = [cl.Buffer(context, mf.READ_WRITE, size=items * n * 4) for _ in range(3)]
        scratch.append(cl.Buffer(context, mf.READ_WRITE, size=items * ring * 4))
        kernel = cl.Kernel(program, "geodesics")
        b = self._buffers
        kernel.set_args(b[0], b[1], b[2], b[3], np.int32(S), np.int32(n), np.float64(1.0 / delta), b[4], b[5],
                        *scratch)
        self._scratch = scratch
        self._event = cl.enqueue_nd_range_kernel(self._queue, kernel, (items,), (1,))
        self._queue.flush()  # start now, not at the first wait
        self._result = None

    def finish(self) -> np.ndarray:
        if self._result is None:
            import pyopencl as cl  # lazily: facepipe runs without an OpenCL driver

            self._event.wait()
            # make the host array current (for a CPU device it already is: the map is free)
            mapped, _ = cl.enqueue_map_buffer(self._queue, self._buffers[5], cl.map_flags.READ, 0,
                                              self._out.shape, self._out.dtype, is_blocking=True)
            mapped.base.release(self._queue)
            self._queue.finish()
            self._result = self._out
            self._release()
        return self._result

    def close(self) -> None:
        """Wait for the kernel if it still runs (its buffers cannot go sooner) and let go."""
        if self._result is None and self._event is not None:
            self._event.wait()
        self._release()

    def _release(self) -> None:
        for buf in self._buffers + self._scratch:
            buf.release()
        self._buffers, self._scratch, self._event = [], [], None


def start(graph: sp.csr_matrix, sources: np.ndarray) -> DeviceGeodesics | None:
    """The distances from ``sources``, started on a CPU device; None where that cannot be done."""
    graph = sp.csr_matrix(graph)
    if graph.nnz >= 2 ** 31 or graph.shape[0] >= 2 ** 31 or len(sources) == 0:
        return None
    sizes = ring_size(graph.data)
    if sizes is None:
        return None
    device = _cpu_device()
    if device is None:
        return None
    try:
        return DeviceGeodesics(graph, sources, device, *sizes)
    except Exception:  # noqa: BLE001 - a driver that fails to build or run it: SciPy does the work
        return None
