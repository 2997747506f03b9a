"""The cost of each stage of an OpenCL replay frame, for the roofline table (bench/roofline.py).

The take runs chunk by chunk with every stage waited for before the next starts, so each one is
timed alone: the host's tables (strain features, the novelty gate's fits), ``large_scale``
(B·u), the fused frames + fine-scale kernel, the copy of the positions out of device memory,
and their write to ``positions.npy``. The fused kernel's parts come from variants of it built
without one or both (``_stages``): frames = (frames only) − (neither), fine scale = (fine
only) − (neither), output = neither (reading the large scale, the head motion, the stores).

Two clocks per stage. Wall: kernel time from the profiling events, host time from
``perf_counter``. Busy: this process's CPU seconds during the stage divided by the threads that
ran it (the device's compute units for a kernel, 1 for a host stage) — the time the stage
would take were its threads never descheduled. On a machine other people's work shares, the
wall clock measures them as much as the replay; the busy clock hardly does (it still counts
cache and memory-bus contention), so the ratios to the roofline use it, and both are reported.
Each figure is the least over ``repeats`` passes (the least disturbed).
"""

from __future__ import annotations

import resource
import time
from pathlib import Path

import numpy as np


def _cpu_seconds() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


class _Clock:
    """Wall and busy seconds per stage, summed over a pass."""

    def __init__(self):
        self.wall: dict = {}
        self.busy: dict = {}

    def add(self, stage: str, wall: float, busy: float) -> None:
        self.wall[stage] = self.wall.get(stage, 0.0) + wall
        self.busy[stage] = self.busy.get(stage, 0.0) + busy


def _kernel(clock: _Clock, stage: str, event, cpu0: float, threads: int | None) -> None:
    """A kernel's wall and busy time; ``threads`` None: a GPU's kernel, busy is its wall time."""
    event.wait()
    wall = (event.profile.end - event.profile.start) * 1e-9
    clock.add(stage, wall, wall if threads is None else (_cpu_seconds() - cpu0) / threads)


def _pass(ev, head, R, t, out: np.ndarray | None, writer_path: Path | None, threads: int | None,
          placed: bool = False) -> _Clock:
    """One pass over the take, stage after stage; ``out`` and ``writer_path`` add the host copy
    and the write (only for the full kernel). ``placed``: the kernel writes the positions into
    the writer's own memory (:meth:`NpyWriter.placement`), as a replay does, else into device
    memory that the writer copies from."""
    import pyopencl as cl

    from facepipe.io.npy_stream import NpyWriter

    clock = _Clock()
    T, C, V = head.shape[0], ev.chunk, ev.V
    slot = ev._slots[0]
    ev._slot_buffers(slot, False, False)
    slot.final = None
    writer = NpyWriter(writer_path, (T, V, 3), regions=ev.placement_regions) if writer_path is not None else None
    try:
        for s in range(0, T, C):
            e = min(T, s + C)
            w0, c0 = time.perf_counter(), _cpu_seconds()
            tables = ev._tables(head[s:e], R[s:e], t[s:e])
            clock.add("host_tables", time.perf_counter() - w0, _cpu_seconds() - c0)
            c0 = _cpu_seconds()
            _kernel(clock, "large_scale", ev._launch_large_scale(slot, tables), c0, threads)
            if placed and writer is not None:
                slot.final, slot.final_offset = ev._host_output(None, writer.placement, s, e, 0)
            c0 = _cpu_seconds()
            _kernel(clock, "fused", ev._launch_fine_scale(slot, e - s, False, False)["last"], c0, threads)
            if out is None and writer is None:
                continue
            buffer, offset = (slot.outputs["final"], 0) if slot.final is None else (slot.final, slot.final_offset)
            arr, map_ev = cl.enqueue_map_buffer(ev.queue, buffer, cl.map_flags.READ, 4 * offset,
                                                (e - s, V, 3), np.float32, is_blocking=True)
            try:
                if out is not None:
                    w0, c0 = time.perf_counter(), _cpu_seconds()
                    out[s:e] = arr
                    clock.add("host_copy", time.perf_counter() - w0, _cpu_seconds() - c0)
                if writer is not None:
                    w0, c0 = time.perf_counter(), _cpu_seconds()
                    writer.write(arr)
                    clock.add("positions_write", time.perf_counter() - w0, _cpu_seconds() - c0)
            finally:
                arr.base.release(ev.queue)
    finally:
        if writer is not None:
            writer.close()
    return clock


def measure_stages(model, head, R, t, work_dir: Path, device=None, chunk: int = 32, vector_width=None,
                   repeats: int = 3, placed: bool = True) -> dict:
    """Per-stage wall and busy milliseconds per frame: {"wall": {stage: ms}, "busy": {...},
    "vector_width", "threads"}.

    Stages: host_tables, large_scale, frames, fine_scale, output, host_copy, positions_write.
    ``placed``: positions written from the writer's own memory (see :func:`_pass`).
    """
    from facepipe.opencl import OpenCLEvaluator

    T = head.shape[0]
    out = np.zeros((T, model.n_vertices, 3), dtype=np.float32)  # touched: no page faults in the timing
    best: dict = {}
    info = {}
    for stages in (3, 0, 1, 2):
        ev = OpenCLEvaluator(model, device=device, chunk=chunk, vector_width=vector_width, _stages=stages)
        threads = max(1, int(ev.cl_device.max_compute_units)) if ev.on_host_cores else None
        info = {"vector_width": ev.vw, "threads": threads or 1, "device": ev.device, "gpu": threads is None}
        full = stages == 3
        _pass(ev, head[:ev.chunk], R, t, None, None, threads)  # compiles for this shape, warms the buffers
        for _ in range(repeats):
            clock = _pass(ev, head, R, t, out if full else None, work_dir / "stages.npy" if full else None, threads,
                          placed)
            for kind in ("wall", "busy"):
                for stage, sec in getattr(clock, kind).items():
                    key = (kind, stages, stage)
                    best[key] = min(best.get(key, float("inf")), sec)
    (work_dir / "stages.npy").unlink(missing_ok=True)
    result = dict(info)
    for kind in ("wall", "busy"):
        def ms(stages, stage):
            return best.get((kind, stages, stage), 0.0) / T * 1e3
        none = ms(0, "fused")
        result[kind] = {"host_tables": ms(3, "host_tables"), "large_scale": ms(3, "large_scale"),
                        "frames": max(0.0, ms(1, "fused") - none), "fine_scale": max(0.0, ms(2, "fused") - none),
                        "output": none, "host_copy": ms(3, "host_copy"), "positions_write": ms(3, "positions_write"),
                        "fused_kernel": ms(3, "fused")}
    return result
