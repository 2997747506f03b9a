"""The OpenCL engine for a mesh cache replayed as a take: the cache's surface is the large scale.

:class:`~facepipe.opencl.engine.OpenCLEvaluator` computes the large scale as rest + B·U on the
device and then, in one fused kernel, the frames, the details and the head motion. For a point
cache the large scale is given: this evaluator uploads each chunk's surface (in head space, in the
device's vertex order and layout) where the ``large_scale`` kernel would have written it, and runs
the same fused kernel — the details in the local frames of the cache's surface, the strain of the
cache's handle vertices, the head's motion put back. The band of the details the cache already
carries (:mod:`facepipe.core.detail_bands`) is left out of the RBF weights once, before the replay
(``details.detail_weights``): the device then evaluates only the added bands, with no work per
frame on the host beyond the surface's upload.
"""

from __future__ import annotations

import time

import numpy as np

from facepipe.opencl.device import _cl
from facepipe.opencl.engine import OpenCLEvaluator

#: Vertices per block when the cache's frames are laid out for the device: a block's frames and
#: table rows (2 × 32 frames × 1024 × 12 bytes) fit a core's L2 cache, where the transposing copy
#: is several times quicker than through memory.
_BLOCK = 1024


def _aligned_zeros(shape: tuple, align: int = 4096) -> np.ndarray:
    """A zeroed float32 array starting on a page boundary (a buffer over host memory is used in
    place only where the device's alignment allows)."""
    size = int(np.prod(shape)) * 4
    raw = np.zeros(size + align, dtype=np.uint8)
    offset = (-raw.ctypes.data) % align
    return raw[offset:offset + size].view(np.float32).reshape(shape)


class OpenCLCacheEvaluator(OpenCLEvaluator):
    """OpenCL replay of a cache's own surface plus details.

    Parameters
    ----------
    model : the baked model.
    cache : facepipe.mocap.mesh_cache.MeshCache (rig units).
    pose : facepipe.pipeline.cache_replay.CachePose of the cache.
    details : facepipe.pipeline.cache_replay.CacheDetails after ``estimate()`` (its
        ``detail_weights``: the added bands' RBF weights), or None to add every band.
    device, chunk : as for :class:`OpenCLEvaluator`.
    """

    def __init__(self, model, cache, pose, details=None, device: str | None = None, chunk: int = 32):
        super().__init__(model, device=device, chunk=chunk,
                         detail_weights=None if details is None else details.detail_weights)
        self.cache, self.pose, self.details = cache, pose, details
        order = self.perm if self.perm is not None else np.arange(self.V)
        self._order = order
        self._rest_padding = model.rest[order].astype(np.float32)[:, :, None]
        self._cursor = 0
        self._surface_buffers = [_aligned_zeros((self.Vp, 3, self.chunk)) for _ in range(self.n_slots)]
        # on a CPU device the kernel reads the host's tables where they are (buffers over them,
        # mapped for writing on a queue of their own, so that filling the next chunk's table does
        # not wait for the chunk in flight): no copy of the surface per chunk; on a GPU they are copied
        self._zero_copy = self.on_host_cores
        if self._zero_copy:
            cl = _cl()
            flags = cl.mem_flags.READ_ONLY | cl.mem_flags.USE_HOST_PTR
            self._surface_cl = [cl.Buffer(self.context, flags, hostbuf=table) for table in self._surface_buffers]
            self._map_queue = cl.CommandQueue(self.context, properties=cl.command_queue_properties.PROFILING_ENABLE)
            self._large.release()  # (the base engine's large-scale buffer is not used)
            self._large = None
        # host time per stage: the handles' tables (strain, gate) and the cache's frames laid out
        # for the device; the surface's copy to the device is the "large_scale" event
        self.stage_seconds["handle_tables"] = 0.0
        self.stage_seconds["surface_table"] = 0.0

    def _surface_table(self, start: int, n: int, to_head: bool, table: np.ndarray) -> np.ndarray:
        """(Vp, 3, C) float32 surface of frames start..start+n in the device's layout: in the cache's
        space, or (``to_head``) in head space, Rᵀ (p − t).

        Block by block of vertices small enough that a block's frames and its table rows stay in
        the core's cache: the cache's frames (in its file's byte order) gathered into the device's
        vertex order, converted to float32 and transposed to vertices × coordinates × frames in
        one copy, into ``table``."""
        frames = self.cache.positions[start:start + n]
        scale = np.float32(self.cache.scale)
        if to_head:
            R = self.pose.rotation[start:start + n].astype(np.float32)
            t = self.pose.translation[start:start + n].astype(np.float32).T[None]
        for v0 in range(0, self.V, _BLOCK):
            v1 = min(v0 + _BLOCK, self.V)
            block = table[v0:v1, :, :n]  # (the padding rows past V stay zero)
            source = frames[:, v0:v1] if self.perm is None else np.take(frames, self._order[v0:v1], axis=1)
            block[...] = source.transpose(1, 2, 0)
            if scale != 1.0:
                block *= scale
            if to_head:
                block -= t
                x, y, z = block[:, 0].copy(), block[:, 1].copy(), block[:, 2].copy()
                for j in range(3):  # (Rᵀ q)_j = Σ_i R_ij q_i, per frame
                    block[:, j] = x * R[:, 0, j] + y * R[:, 1, j] + z * R[:, 2, j]
        table[:self.V, :, n:] = self._rest_padding  # padding frames: the rest pose, as large_scale does
        return table

    def _enqueue(self, slot, head, R, t, with_large: bool, with_normals: bool) -> dict:
        """The chunk's tables and surface uploaded, then the fused kernel (no ``large_scale`` kernel).

        With the head motion kept (``R`` given: the pose's) the cache's own surface is used as it
        is and the kernel's rigid motion is the identity: the local frames turn with the surface
        and the strain comes from the head-space handles, so the details are those of the head
        space turned by R, without moving the surface into head space and back. Without it (the
        head motion removed) the surface is moved into head space."""
        cl = _cl()
        q, n = self.queue, head.shape[0]
        t0 = time.perf_counter()
        tables = self._tables(head, None, None)
        t1 = time.perf_counter()
        # two tables in turn, one per chunk in flight: the one of the chunk before last, whose
        # kernel has finished (the stream retires it before this chunk is enqueued)
        k = self._cursor // self.chunk % len(self._surface_buffers)
        if self._zero_copy:
            table, _ = cl.enqueue_map_buffer(self._map_queue, self._surface_cl[k], cl.map_flags.WRITE, 0,
                                             self._surface_buffers[k].shape, np.float32, is_blocking=True)
            self._surface_table(self._cursor, n, R is None, table)
            ev_large = table.base.release(self._map_queue)
            large, surface = self._surface_cl[k], None
        else:
            surface = self._surface_table(self._cursor, n, R is None, self._surface_buffers[k])
            ev_large = cl.enqueue_copy(q, self._large, surface, is_blocking=False)
            large = self._large
        self._cursor += n
        self.stage_seconds["handle_tables"] += t1 - t0
        self.stage_seconds["surface_table"] += time.perf_counter() - t1
        uploads = [cl.enqueue_copy(q, slot.inputs[name], v, is_blocking=False) for name, v in tables.items()]
        slot.host = dict(tables, surface=surface)  # must outlive the non-blocking uploads
        events = self._launch_fine_scale(slot, n, with_large, with_normals, wait_for=uploads + [ev_large],
                                         large=large)
        events["large_scale"] = ev_large
        return events

    def stream(self, head, sink, R=None, t=None, with_large: bool = False, with_normals: bool = False,
               destination=None, placement=None) -> None:
        """As :meth:`OpenCLEvaluator.stream` over the cache's frames from the first (``head``: the pose's
        handles); the details are those of the added bands (the weights given at construction).

        With the head motion kept the large scale is the cache's own surface: handed to ``sink``
        from the cache (its file's rows, converted where the sink copies them), not stored by the
        device and read back."""
        self._cursor = 0
        if not (with_large and R is not None):
            super().stream(head, sink, R, t, with_large=with_large, with_normals=with_normals,
                           destination=destination, placement=placement)
            return
        cache = self.cache

        def with_cache_surface(start, final, large, normals):
            surface = cache.positions[start:start + final.shape[0]]
            if cache.scale != 1.0:
                surface = np.asarray(surface, dtype=np.float32) * np.float32(cache.scale)
            sink(start, final, surface, normals)

        super().stream(head, with_cache_surface, R, t, with_large=False, with_normals=with_normals,
                       destination=destination, placement=placement)
