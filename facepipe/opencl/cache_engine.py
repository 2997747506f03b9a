"""The OpenCL engine for a mesh cache replayed as a take: the cache's surface is the large scale.

:class:`~facepipe.opencl.engine.OpenCLEvaluator` computes the large scale as rest + B·U on the
device and then, in one fused kernel, the frames, the details and the head motion. For a point
cache the large scale is given: this evaluator uploads each chunk's surface (in head space, in the
device's vertex order and layout) where the ``large_scale`` kernel would have written it, and runs
the same fused kernel — the details in the local frames of the cache's surface, the strain of the
cache's handle vertices, the head's motion put back. The band of the details the cache already
carries (:mod:`facepipe.core.detail_bands`) is left out on the host afterwards, where the chosen
bands need it (one multi-right-hand-side solve per chunk and band edge, with a factor made once
per replay, in single precision); when every band is added nothing is done on the host.
"""

from __future__ import annotations

import time

import numpy as np

from facepipe.opencl.device import _cl
from facepipe.opencl.engine import OpenCLEvaluator

#: Vertices per block when the cache's frames are laid out for the device (a few MB: in cache).
_BLOCK = 4096


class OpenCLCacheEvaluator(OpenCLEvaluator):
    """OpenCL replay of a cache's own surface plus details.

    Parameters
    ----------
    model : the baked model.
    cache : facepipe.mocap.mesh_cache.MeshCache (rig units).
    pose : facepipe.pipeline.cache_replay.CachePose of the cache.
    details : facepipe.pipeline.cache_replay.CacheDetails after ``estimate()`` (its ``keep`` and
        ``bands``), or None to add every band.
    device, chunk : as for :class:`OpenCLEvaluator`.
    """

    def __init__(self, model, cache, pose, details=None, device: str | None = None, chunk: int = 32):
        super().__init__(model, device=device, chunk=chunk)
        self.cache, self.pose, self.details = cache, pose, details
        order = self.perm if self.perm is not None else np.arange(self.V)
        self._order = order
        self._rest_padding = model.rest[order].astype(np.float32)[:, :, None]
        self._cursor = 0
        self._surface_buffers = [np.zeros((self.Vp, 3, self.chunk), dtype=np.float32) for _ in range(self.n_slots)]
        self.stage_seconds["upload_surface"] = 0.0
        self.stage_seconds["bands"] = 0.0

    def _surface_table(self, start: int, n: int) -> np.ndarray:
        """(Vp, 3, C) float32 head-space surface of frames start..start+n in the device's layout.

        In float32 (the device's precision), block by block of vertices so every step works in
        cache: the cache's frames gathered into the device's vertex order and transposed to
        vertices × coordinates × frames, then moved into head space, Rᵀ (p − t), with the frames
        along the contiguous axis. Two tables are used in turn (one per chunk in flight), so no
        chunk allocates fresh memory."""
        C = self.chunk
        R = self.pose.rotation[start:start + n].astype(np.float32)
        t = self.pose.translation[start:start + n].astype(np.float32)
        table = self._surface_buffers[self._cursor // C % len(self._surface_buffers)]
        frames = self.cache.positions[start:start + n]
        for v0 in range(0, self.V, _BLOCK):
            block = table[v0:min(v0 + _BLOCK, self.V), :, :n]  # (the padding rows past V stay zero)
            block[...] = np.asarray(frames[:, self._order[v0:v0 + _BLOCK]], dtype=np.float32).transpose(1, 2, 0)
            if self.cache.scale != 1.0:
                block *= np.float32(self.cache.scale)
            block -= t.T[None]
            x, y, z = block[:, 0].copy(), block[:, 1].copy(), block[:, 2].copy()
            for j in range(3):  # (Rᵀ q)_j = Σ_i R_ij q_i, per frame
                block[:, j] = x * R[:, 0, j] + y * R[:, 1, j] + z * R[:, 2, j]
        table[:self.V, :, n:] = self._rest_padding  # padding frames: the rest pose, as large_scale does
        return table

    def _enqueue(self, slot, head, R, t, with_large: bool, with_normals: bool) -> dict:
        """The chunk's tables and surface uploaded, then the fused kernel (no ``large_scale`` kernel)."""
        cl = _cl()
        q, n = self.queue, head.shape[0]
        t0 = time.perf_counter()
        tables = self._tables(head, R, t)
        surface = self._surface_table(self._cursor, n)
        self._cursor += n
        self.stage_seconds["upload_surface"] += time.perf_counter() - t0
        uploads = [cl.enqueue_copy(q, slot.inputs[k], v, is_blocking=False) for k, v in tables.items()]
        ev_large = cl.enqueue_copy(q, self._large, surface, is_blocking=False)
        slot.host = dict(tables, surface=surface)  # must outlive the non-blocking uploads
        events = self._launch_fine_scale(slot, n, with_large, with_normals, wait_for=uploads + [ev_large])
        events["large_scale"] = ev_large
        return events

    def stream(self, head, sink, R=None, t=None, with_large: bool = False, with_normals: bool = False,
               destination=None, placement=None) -> None:
        """As :meth:`OpenCLEvaluator.stream` over the cache's frames (``head``: the pose's handles); the
        bands the cache carries are taken out of the details on the host before ``sink``."""
        self._cursor = 0
        keep = None if self.details is None else self.details.keep
        partial = keep is not None and not np.all(keep == 1.0)
        if not partial:
            super().stream(head, sink, R, t, with_large=with_large, with_normals=with_normals,
                           destination=destination, placement=placement)
            return
        # (with bands to take out, the final positions are made on the host: no placement)

        def banded(start, final, large, normals):
            t0 = time.perf_counter()
            # in float32, the device's precision: the band solve is single precision too (DetailBands)
            large = np.asarray(large, dtype=np.float32)
            final = large + self.details.bands.combine(np.asarray(final, dtype=np.float32) - large, keep)
            if destination is not None:
                destination[start:start + final.shape[0]] = final
                final = destination[start:start + final.shape[0]]
            self.stage_seconds["bands"] += time.perf_counter() - t0
            sink(start, final, large if with_large else None, normals)

        super().stream(head, banded, R, t, with_large=True, with_normals=with_normals)
