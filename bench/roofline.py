"""Rooflines for the replay benchmark: this machine's limits, measured in the same run.

Two limits bound every stage of a replay frame:

* arithmetic: the FMA peak, measured with an OpenCL kernel of independent multiply-add chains
  on the device the replay uses (so the figure includes what that device's compiler makes of
  vector code), and, as a second, independent figure, with a float32 matrix product in NumPy's
  BLAS; the computed peak (cores × FMA pipes × lanes × 2 × clock) is recorded beside them;
* memory: the rate of a large ``memcpy`` (bytes read + written per second), and for the
  positions written, the disk's rate for direct writes from an aligned buffer.

:func:`stage_table` sets each stage's measured time per frame against ``max(FLOP / peak,
bytes / rate)`` — the time the stage could take if it ran at the limit it is nearest to — and
names that limit. A ratio of 1 is at the roofline; 1.5 is the issue's bar.
"""

from __future__ import annotations

import mmap
import os
import resource
import tempfile
import time
from pathlib import Path

import numpy as np

from bench.timing import median_time

#: independent accumulators per work-item in the FMA kernel: enough to cover the FMA latency
#: (4–5 cycles) on 2 pipes
_CHAINS = 16
_FMA_SOURCE = r"""
#define CAT_(a, b) a##b
#define CAT(a, b) CAT_(a, b)
typedef CAT(float, VW) vfloat;
__kernel void fma_peak(__global float *out, const int iterations, const float a, const float b)
{
    vfloat acc[CHAINS];
#pragma unroll
    for (int i = 0; i < CHAINS; ++i)
        acc[i] = (vfloat)(get_global_id(0) + i);
    const vfloat va = (vfloat)(a), vb = (vfloat)(b);
    for (int k = 0; k < iterations; ++k) {
#pragma unroll
        for (int i = 0; i < CHAINS; ++i)
            acc[i] = acc[i] * va + vb;
    }
    vfloat s = acc[0];
#pragma unroll
    for (int i = 1; i < CHAINS; ++i)
        s += acc[i];
    /* one store per work-item, so nothing is optimised away */
    out[get_global_id(0)] = s.s0 + s.s1;
}
"""


def _cpu_seconds() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def fma_kernel(context, vector_width: int):
    """The FMA-chain kernel: ``fma_peak(out, iterations, a, b)`` leaves in out[i] the sum over the
    chains c of lanes 0 and 1 of ``iterations`` steps x ← a·x + b from x = i + c."""
    import pyopencl as cl

    program = cl.Program(context, _FMA_SOURCE).build(
        options=[f"-DVW={int(vector_width)}", f"-DCHAINS={_CHAINS}", "-cl-mad-enable"])
    return cl.Kernel(program, "fma_peak")


def opencl_fma_peak_gflops(context, device, vector_width: int = 8, iterations: int = 20000,
                           repeats: int = 5) -> dict:
    """FLOP/s (GFLOP/s) of independent FMA chains on ``device``, the best of ``repeats`` launches:
    {"wall": by the kernel's own time, "busy": by this process's CPU time ÷ compute units (a CPU
    device; the time were its threads never descheduled — see bench/replay_stages.py)}.

    Each work-item runs ``_CHAINS`` independent vectors of ``vector_width`` floats through
    ``iterations`` multiply-adds (2 FLOP each); the work covers every compute unit several times.
    """
    import pyopencl as cl

    kernel = fma_kernel(context, vector_width)
    queue = cl.CommandQueue(context, properties=cl.command_queue_properties.PROFILING_ENABLE)
    gpu = bool(device.type & cl.device_type.GPU)
    items = int(device.max_compute_units) * (2048 if gpu else 8)
    out = cl.Buffer(context, cl.mem_flags.WRITE_ONLY, size=4 * items)
    kernel.set_args(out, np.int32(iterations), np.float32(0.999), np.float32(1e-3))
    flop = 2.0 * vector_width * _CHAINS * iterations * items
    wall = busy = 0.0
    for _ in range(repeats + 1):  # the first launch warms up (thread pool, page faults)
        c0 = _cpu_seconds()
        ev = cl.enqueue_nd_range_kernel(queue, kernel, (items,), None)
        ev.wait()
        cpu = (_cpu_seconds() - c0) / max(1, int(device.max_compute_units))
        wall = max(wall, flop / ((ev.profile.end - ev.profile.start) * 1e-9) / 1e9)
        if not gpu and cpu > 0:
            busy = max(busy, flop / cpu / 1e9)
    return {"wall": wall, "busy": busy if not gpu else wall}


def numpy_fma_peak_gflops(n: int = 1024, repeats: int = 5) -> float:
    """FLOP/s (GFLOP/s) of a float32 n × n matrix product in NumPy's BLAS (2 n³ FLOP), best of ``repeats``."""
    a = np.random.default_rng(0).random((n, n), dtype=np.float32)
    b = a.T.copy()
    c = np.empty_like(a)
    np.matmul(a, b, out=c)
    best = min(median_time(lambda: np.matmul(a, b, out=c), 1) for _ in range(repeats))
    return 2.0 * n ** 3 / best / 1e9


def computed_fma_peak_gflops() -> dict:
    """The peak from the CPU's description: cores × 2 FMA pipes × lanes × 2 FLOP × clock.

    Lanes from the widest vector flag in /proc/cpuinfo (avx512f: 16 floats, avx2/fma: 8,
    else 4); the clock is the highest "cpu MHz" listed (a VM often shows the base clock). The
    two FMA pipes per core are an assumption (true of current x86 server cores), which is why
    the measured figures are the ones the table uses.
    """
    mhz, flags = 0.0, set()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("cpu MHz"):
                mhz = max(mhz, float(line.split(":")[1]))
            elif line.startswith("flags") and not flags:
                flags = set(line.split(":")[1].split())
    except OSError:
        pass
    lanes = 16 if "avx512f" in flags else 8 if "fma" in flags else 4
    cores = os.cpu_count() or 1
    return {"cores": cores, "fma_pipes_per_core": 2, "float_lanes": lanes, "mhz": mhz,
            "gflops": cores * 2 * lanes * 2 * mhz / 1e3}


def copy_rate_gbs(megabytes: int = 256, repeats: int = 5) -> dict:
    """This machine's memory bandwidth as seen by a large single-threaded copy, (read + written)
    bytes / s in GB/s, the best of ``repeats``: {"wall", "busy" (by CPU time)}."""
    a = np.ones(megabytes * 2**20 // 4, dtype=np.float32)
    b = np.empty_like(a)
    np.copyto(b, a)
    wall = busy = float("inf")
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), _cpu_seconds()
        np.copyto(b, a)
        wall, busy = min(wall, time.perf_counter() - t0), min(busy, max(_cpu_seconds() - c0, 1e-6))
    return {"wall": 2 * a.nbytes / wall / 1e9, "busy": 2 * a.nbytes / busy / 1e9}


_COPY_SOURCE = r"""
__kernel void copy16(__global const float16 *restrict src, __global float16 *restrict dst)
{
    const size_t i = get_global_id(0);
    dst[i] = src[i];
}
"""


def device_copy_rate_gbs(context, device, megabytes: int = 256, repeats: int = 5) -> dict:
    """The device's own memory bandwidth, a copy kernel over all its compute units, (read +
    written) bytes / s in GB/s, the best of ``repeats``: {"wall", "busy"} (busy: by this
    process's CPU time ÷ compute units on a CPU device; the wall figure on a GPU). A kernel, not
    clEnqueueCopyBuffer: a CPU driver may copy buffers on one thread, the replay's kernels run
    on all."""
    import pyopencl as cl

    queue = cl.CommandQueue(context, properties=cl.command_queue_properties.PROFILING_ENABLE)
    nbytes = megabytes * 2**20
    a = cl.Buffer(context, cl.mem_flags.READ_WRITE, size=nbytes)
    b = cl.Buffer(context, cl.mem_flags.READ_WRITE, size=nbytes)
    cl.enqueue_fill_buffer(queue, a, np.float32(1.0), 0, nbytes).wait()
    kernel = cl.Kernel(cl.Program(context, _COPY_SOURCE).build(), "copy16")
    kernel.set_args(a, b)
    gpu = bool(device.type & cl.device_type.GPU)
    wall = busy = float("inf")
    for _ in range(repeats + 1):  # the first pass also faults the destination's pages in
        c0 = _cpu_seconds()
        ev = cl.enqueue_nd_range_kernel(queue, kernel, (nbytes // 64,), None)
        ev.wait()
        cpu = (_cpu_seconds() - c0) / max(1, int(device.max_compute_units))
        wall = min(wall, (ev.profile.end - ev.profile.start) * 1e-9)
        busy = min(busy, max(cpu, 1e-6))
    wall_gbs = 2 * nbytes / wall / 1e9
    return {"wall": wall_gbs, "busy": wall_gbs if gpu else 2 * nbytes / busy / 1e9}


def direct_write_rate_gbs(folder: Path, megabytes: int = 256, block: int = 16 << 20) -> float | None:
    """The disk's rate (GB/s) for direct writes (O_DIRECT) from one aligned buffer, no copy; None
    where the file system refuses direct I/O."""
    if not hasattr(os, "O_DIRECT"):
        return None
    buf = mmap.mmap(-1, block)
    buf.write(b"\x01" * block)
    fd_path = None
    try:
        with tempfile.NamedTemporaryFile(dir=folder, delete=False) as fh:
            fd_path = fh.name
        try:
            fd = os.open(fd_path, os.O_WRONLY | os.O_TRUNC | os.O_DIRECT)
        except OSError:
            return None
        try:
            t0 = time.perf_counter()
            for _ in range(max(1, megabytes * 2**20 // block)):
                os.write(fd, buf)
            os.fsync(fd)
            seconds = time.perf_counter() - t0
        except OSError:
            return None
        finally:
            os.close(fd)
        return max(1, megabytes * 2**20 // block) * block / seconds / 1e9
    finally:
        buf.close()
        if fd_path:
            Path(fd_path).unlink(missing_ok=True)


def stage_flops(V: int, H: int, P: int, K: float, ring: float, method: str, fans: float = 1.0) -> dict:
    """Floating-point operations per frame of each replay stage, counted from the kernels' source
    (a multiply-add is 2; a square root or division 1).

    large_scale: 3 coordinates × H multiply-adds per vertex. frames: per fan entry (``ring``
    faces and ``fans`` fan starts per vertex) the neighbour's difference (3), per face the cross
    product summed (6 multiply-adds); a normalisation (~10); the tangent: the edge (3), its
    normal part (5 + 6), two lengths (~12), a normalisation (~10), the bitangent (9). fine_scale
    (WPSD, the square expanded): per used edge α·f (1), its square's multiply-add (2), a
    multiply-add per pose (2) and the gate's (2); per pose the sum, the clamp and the square root
    (3) and 3 multiply-adds for the RBF sum; the detail to the frame (15). output: the head
    motion (9 multiply-adds, 3 adds).
    """
    frames = (ring + fans) * 3 + ring * 12 + 10 + 3 + 11 + 12 + 10 + 9
    if method == "none":
        fine = 0.0
    elif method == "psd":
        fine = P * 6 + 15
    else:
        fine = K * (2 * P + 5) + P * 3 + P * 6 + 15
    return {"large_scale": V * H * 3 * 2.0, "frames": V * frames, "fine_scale": V * fine, "output": V * 21.0,
            "host_copy": 0.0, "positions_write": 0.0}


#: stages that run on the host's CPU (their memory limit is the host's copy rate, not the device's)
HOST_STAGES = ("host_tables", "host_copy", "positions_write")


def stage_table(stage_ms: dict, flops: dict, nbytes: dict, peak_gflops: float, copy_gbs: float,
                write_gbs: float | None = None, device_copy_gbs: float | None = None) -> dict:
    """Each stage against its roofline: {stage: {ms, gflop, mb, limit_ms, bound, ratio}}.

    ``limit_ms`` = max(FLOP / peak, bytes / rate): the rate is the device's copy rate for a
    kernel (``device_copy_gbs``, when known), the host's (``copy_gbs``) for the host stages,
    the disk's for ``positions_write`` when ``write_gbs`` is known; ``bound`` names the larger
    term; ``ratio`` = measured / limit (1: at the roofline).
    """
    table = {}
    for stage, ms in stage_ms.items():
        f = float(flops.get(stage, 0.0))
        b = float(nbytes.get(stage, 0.0))
        if stage == "positions_write" and write_gbs:
            rate = write_gbs
        elif stage in HOST_STAGES or not device_copy_gbs:
            rate = copy_gbs
        else:
            rate = device_copy_gbs
        compute_ms = f / (peak_gflops * 1e9) * 1e3 if peak_gflops else 0.0
        memory_ms = b / (rate * 1e9) * 1e3 if rate else 0.0
        limit = max(compute_ms, memory_ms)
        bound = "compute" if compute_ms >= memory_ms else ("disk" if rate is write_gbs else "memory")
        table[stage] = {"ms_per_frame": ms, "gflop_per_frame": f / 1e9, "mb_per_frame": b / 1e6,
                        "limit_ms_per_frame": limit, "bound": bound,
                        "ratio_to_limit": ms / limit if limit > 0 else None,
                        "gflop_per_s": f / (ms * 1e-3) / 1e9 if ms > 0 and f else None,
                        "gb_per_s": b / (ms * 1e-3) / 1e9 if ms > 0 and b else None}
    return table


def format_table(table: dict, title: str) -> str:
    """The stage table as text, one stage a line."""
    lines = [title, f"  {'stage':16s} {'ms/frame':>9s} {'GFLOP':>7s} {'MB':>7s} {'GFLOP/s':>8s} {'GB/s':>6s} "
                    f"{'limit ms':>9s} {'bound':>8s} {'× limit':>8s}"]
    for stage, row in table.items():
        def num(x, fmt):
            return format(x, fmt) if x is not None else "-"
        lines.append(f"  {stage:16s} {row['ms_per_frame']:9.3f} {row['gflop_per_frame']:7.3f} "
                     f"{row['mb_per_frame']:7.2f} {num(row['gflop_per_s'], '8.1f')} {num(row['gb_per_s'], '6.1f')} "
                     f"{row['limit_ms_per_frame']:9.3f} {row['bound']:>8s} {num(row['ratio_to_limit'], '8.2f')}")
    return "\n".join(lines)
