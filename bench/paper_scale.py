"""Benchmarks: bake and replay speed on a generated sample rig, against a per-frame solve.

``python -m bench.paper_scale`` (``make bench``) generates the sample rig (``facepipe sample``), bakes it in a
child process (time and peak memory of the bake alone), then, in this process, replays the
take's handles with the OpenCL engine (positions kept in memory, and written to positions.npy
through :func:`facepipe.pipeline.replay.replay`), with the NumPy reference, and with the baseline the
paper replaced: factor the shell once, back-substitute u_H every frame. All figures come from
one run on one machine, so the ratios compare like with like; timings are medians of
``repeats`` runs. Tests never assert times.

Per stage (bench/replay_stages.py: every stage waited for and timed alone, by the wall clock and
by CPU time ÷ the device's threads), each stage's FLOP and bytes per frame are set against this
machine's limits measured in the same run (bench/roofline.py: FMA peak, copy rates, disk), before
(8-frame vectors, positions copied) and after (the device's own width, positions written in
place), as a table printed and kept in the JSON.
"""

from __future__ import annotations

import json
import os
import platform
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

import click
import numpy as np

from bench.timing import median_time
from facepipe.io.atomic import atomic_path


def _peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _cpu_name() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def _load() -> list[float]:
    try:
        return [round(x, 2) for x in os.getloadavg()]
    except OSError:
        return []


# ----------------------------------------------------------------------------- child processes

# The bake runs in a child so that its peak memory is its own (the bench process holds replay
# buffers); it is what `facepipe bake CONFIG` does, with the phases timed.
_BAKE_CHILD = r"""
import json, resource, sys, time
t0 = time.perf_counter()
from facepipe.pipeline.fit import fit_config
from facepipe.pipeline.tune import choose_parameters
from facepipe.io.model_file import add_model_arrays, geometry_to, model_arrays
from facepipe.io.npz_file import NpzWriter
validation = {}
def validate(rig, geodesics):
    t = time.perf_counter()
    report = choose_parameters(rig, sys.argv[3] == "validate", geodesics=geodesics)
    validation.update(seconds=time.perf_counter() - t, validated=report["validated"],
                      chosen=report.get("chosen"), reason=report.get("reason"),
                      stages=report.get("seconds"))
with NpzWriter(sys.argv[2]) as npz:  # as `facepipe bake` writes it: the geometry while the details are fitted
    rig, fit = fit_config(sys.argv[1], prepare=validate, early_basis=sys.argv[3] == "fixed",
                          on_geometry=geometry_to(npz))
    t2 = time.perf_counter()
    t1 = t2 - fit.report["seconds"]["total"] - validation["seconds"]
    arrays, meta = model_arrays(fit, rig)
    add_model_arrays(npz, arrays, meta)
t3 = time.perf_counter()
own, helpers = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
cpu = own.ru_utime + own.ru_stime + helpers.ru_utime + helpers.ru_stime  # a shared machine stretches the wall time
print(json.dumps({"load": t1 - t0, "fit": t2 - t1, "save": t3 - t2, "total": t3 - t0, "validation": validation,
                  "cpu_seconds": cpu,
                  "fit_phases": fit.report.get("seconds", {}), "geodesics": fit.report.get("geodesics"),
                  "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
                  "helper_peak_rss_mb": resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024.0}))
"""


def _run_child(args: list[str], log) -> str:
    proc = subprocess.run(args, capture_output=True, text=True)
    if proc.returncode != 0:
        log(proc.stdout[-2000:] + proc.stderr[-4000:])
        raise RuntimeError(f"benchmark step failed: {' '.join(args[:4])} ...")
    return proc.stdout


def _sample(rig_dir: Path, params: dict, log) -> None:
    """Generate the rig unless the folder already holds one made with the same parameters."""
    stamp = rig_dir / "bench_params.json"
    if stamp.is_file() and json.loads(stamp.read_text()) == params and (rig_dir / "sample.toml").is_file():
        log(f"sample rig: reusing {rig_dir}")
        return
    t0 = time.perf_counter()
    args = [sys.executable, "-m", "facepipe", "sample", str(rig_dir), "--vertices", str(params["vertices"]),
            "--examples", str(params["examples"]), "--frames", str(params["frames"]), "-q"]
    if params["markers"]:
        args += ["--markers", str(params["markers"])]
    _run_child(args, log)
    stamp.write_text(json.dumps(params))
    log(f"sample rig: {params['vertices']} vertices requested ({time.perf_counter() - t0:.1f} s)")


# ----------------------------------------------------------------------------- bandwidth


def machine_limits(work_dir: Path, device, log) -> dict:
    """The rooflines of this run: FMA peak (OpenCL on the replay's device at its vector width,
    NumPy's BLAS, computed), memory copy rate, direct-write disk rate (bench/roofline.py)."""
    from bench.roofline import (computed_fma_peak_gflops, copy_rate_gbs, device_copy_rate_gbs, direct_write_rate_gbs,
                                numpy_fma_peak_gflops, opencl_fma_peak_gflops)
    from facepipe.opencl.device import open_device

    context, dev = open_device(device)
    gpu = bool(dev.type & 4)  # CL_DEVICE_TYPE_GPU
    width = 1 if gpu else (16 if dev.preferred_vector_width_float >= 16 else 8)
    fma = opencl_fma_peak_gflops(context, dev, max(width, 4) if not gpu else 4)
    limits = {"fma_gflops": fma, "fma_vector_width": width, "numpy_matmul_gflops": numpy_fma_peak_gflops(),
              "computed_fma_peak": computed_fma_peak_gflops(), "copy_gbs": copy_rate_gbs(),
              "device_copy_gbs": device_copy_rate_gbs(context, dev), "disk_write_gbs": direct_write_rate_gbs(work_dir)}
    c = limits["computed_fma_peak"]
    log(f"FMA peak: {fma['busy']:.0f} GFLOP/s by CPU time, {fma['wall']:.0f} by the wall clock (OpenCL, "
        f"{max(width, 4)}-float vectors); NumPy float32 matmul {limits['numpy_matmul_gflops']:.0f}; computed "
        f"{c['gflops']:.0f} ({c['cores']} cores × 2 FMA × {c['float_lanes']} lanes × {c['mhz']:.0f} MHz)")
    disk = limits["disk_write_gbs"]
    d = limits["device_copy_gbs"]
    log(f"memory copy rate (read + write): host memcpy {limits['copy_gbs']['busy']:.1f} GB/s by CPU time, "
        f"{limits['copy_gbs']['wall']:.1f} by the wall clock; device buffer copy {d['busy']:.1f} GB/s by CPU time, "
        f"{d['wall']:.1f} by the wall clock; direct writes to disk: "
        + (f"{disk:.2f} GB/s" if disk else "not available"))
    return limits


def stage_bytes(V: int, H: int, P: int, K: float, chunk: int, method: str, fan_entries: float = 7.0) -> dict:
    """Bytes each stage must move per frame at least (each array read or written once).

    large_scale: B once per chunk, the large-scale positions written; frames: those positions
    read, the fans (``fan_entries`` per vertex) and the tangent's neighbour once per chunk;
    fine_scale: per-vertex WPSD edges (K used of them), distance constants and RBF weights once
    per chunk; output: positions read, final positions written (plus the write-allocate read of
    the destination).
    """
    pos = V * 3 * 4
    return {
        "large_scale": V * H * 4 / chunk + pos,
        "frames": pos + V * (4 + fan_entries * 4 + 4) / chunk,
        "fine_scale": 0.0 if method == "none" else V * (K * 8 + 4 + P * 16 + 12) / chunk,
        "output": pos + 2 * pos,
    }


# ----------------------------------------------------------------------------- the bench


def run_bench(work_dir: Path, n_vertices: int = 20000, n_frames: int = 64, repeats: int = 3, chunk: int = 32,
              n_markers: int | None = None, n_examples: int = 6, device: str | None = None,
              numpy_frames: int = 8, baseline_frames: int = 8, bake_repeats: int = 3, use_kit: bool = True,
              exr_resolution: int = 2048, log=print) -> dict:
    """Generate a sample rig, bake it, and time replay (OpenCL, NumPy) and the per-frame solve baseline.

    Parameters
    ----------
    work_dir : folder for the rig, the model and replay outputs (the rig is reused when its
        parameters match).
    n_vertices, n_markers, n_examples, n_frames : the sample rig (``facepipe sample``).
    repeats : runs per timing (the median is reported).
    bake_repeats : bakes timed (the median run is reported); more than ``repeats``, as a bake
        is one long run that a busy moment of a shared machine can stretch.
    chunk : frames per OpenCL launch.
    numpy_frames, baseline_frames : frames for the slow paths (NumPy reference, per-frame solve).
    use_kit : measure exports and the 2D lift on the ICT kit when ../shared is there (a real scan
        and take); False: on the generated rig alone (a quick run).
    exr_resolution : the displacement maps' size per UDIM tile in the export figures.

    Returns
    -------
    dict of figures (seconds, frames/s, MB, GB/s), JSON-serialisable.
    """
    from facepipe.io.model_file import load_model
    from facepipe.pipeline.replay import NumpyEvaluator, stream_chunks

    work_dir = Path(work_dir)
    rig_dir = work_dir / "rig"
    load_start = _load()
    _sample(rig_dir, {"vertices": n_vertices, "examples": n_examples, "frames": n_frames, "markers": n_markers}, log)

    # ---- bake, in a child, `bake_repeats` times: the run with the median time is reported
    model_path = work_dir / "model.npz"
    # the baseline in the same run, interleaved with it: the bake without the shell's basis solved
    # while the examples load (its factorisation after the load, as before that overlap)
    runs: dict[str, list] = {"fixed": [], "fixed-serial": []}
    for _ in range(max(1, bake_repeats)):
        for mode in runs:
            args = [sys.executable, "-c", _BAKE_CHILD, str(rig_dir / "sample.toml"), str(model_path), mode]
            runs[mode].append(json.loads(_run_child(args, log).strip().splitlines()[-1]))
    bakes, serial = (sorted(runs[mode], key=lambda b: b["total"]) for mode in runs)
    bake, serial_bake = bakes[len(bakes) // 2], serial[len(serial) // 2]
    bake["runs"] = [round(b["total"], 2) for b in bakes]
    log(f"bake: {bake['total']:.1f} s (load {bake['load']:.1f}, fit {bake['fit']:.1f}, save {bake['save']:.1f}; "
        f"median of {', '.join(f'{t:.1f}' for t in bake['runs'])} s), peak {bake['peak_rss_mb'] / 1024:.2f} GB "
        f"(+ {bake['helper_peak_rss_mb'] / 1024:.2f} GB in the largest helper process); without the basis "
        f"solved during the load {serial_bake['total']:.1f} s (median of "
        f"{', '.join('%.1f' % b['total'] for b in serial)} s)")
    # ---- what `facepipe bake CONFIG` does by default: the parameters validated first (timed once; the
    # replay below uses the fixed-parameter model, whose basis size does not depend on the choice)
    validated = json.loads(_run_child([sys.executable, "-c", _BAKE_CHILD, str(rig_dir / "sample.toml"),
                                       str(work_dir / "model_validated.npz"), "validate"], log).strip().splitlines()[-1])
    v = validated["validation"]
    log(f"validated bake: {validated['total']:.1f} s ({validated['cpu_seconds']:.1f} s of CPU), of which validation "
        f"{v['seconds']:.1f} s "
        + (f"(shell {v['stages']['shell']:.1f}, details {v['stages']['details']:.1f}); chosen {v['chosen']}"
           if v["validated"] else f"(not validated: {v['reason']})"))
    phases = bake["fit_phases"]
    log("  fit: " + ", ".join(f"{k} {v:.1f}" for k, v in phases.items() if k not in ("total", "load")
                              and not k.endswith("_sources")) + " s"
        + ("; the handles' geodesics ran on the OpenCL CPU device" if bake.get("geodesics") == "opencl" else
           f"; a second process took {phases['geodesics_child_sources']:.0f} of the handles' geodesics"
           if bake.get("geodesics") == "process" else ""))

    bake_phases = {"load": bake["load"], **{k: v for k, v in phases.items() if k not in ("total", "load")
                                             and not k.endswith("_sources")}, "save": bake["save"]}
    log("bake phases (the median bake):\n" + "\n".join(f"  {k:16s} {v:6.2f} s" for k, v in bake_phases.items())
        + f"\n  {'total':16s} {bake['total']:6.2f} s ({bake['cpu_seconds']:.1f} s of CPU)")

    model = load_model(model_path)
    V, H = model.n_vertices, int(len(model.handle_vertices))
    P, F = int(model.basis_features.shape[0]), int(len(model.edges))
    K_used = float((model.edge_weight > 0).sum(axis=1).mean())
    truth = np.load(rig_dir / "take_truth.npz")["positions"]
    head = truth[:, model.handle_vertices].astype(np.float64)
    del truth
    T = head.shape[0]
    R = np.broadcast_to(np.eye(3), (T, 3, 3)).copy()
    t = np.zeros((T, 3))
    config = {"vertices": V, "triangles": int(len(model.triangles)), "handles": H, "feature_edges": F,
              "basis_poses": P, "method": model.method, "wpsd_edges_per_vertex": K_used, "frames": T,
              "repeats": repeats, "bake_repeats": bake_repeats, "chunk": chunk}
    log(f"model: V = {V}, H = {H}, F = {F}, P = {P} ({model.method}), {K_used:.1f} WPSD edges per vertex")

    results = {"config": config, "bake": {"seconds": bake["total"], "load_seconds": bake["load"],
                                          "fit_seconds": bake["fit"], "save_seconds": bake["save"],
                                          "fit_phases": bake["fit_phases"], "phases_seconds": bake_phases,
                                          "geodesics": bake.get("geodesics"),
                                          "runs_seconds": bake["runs"], "cpu_seconds": bake["cpu_seconds"],
                                          "peak_rss_mb": bake["peak_rss_mb"],
                                          "helper_peak_rss_mb": bake["helper_peak_rss_mb"],
                                          "without_early_basis": {
                                              "seconds": serial_bake["total"], "cpu_seconds": serial_bake["cpu_seconds"],
                                              "runs_seconds": [round(b["total"], 2) for b in serial],
                                              "peak_rss_mb": serial_bake["peak_rss_mb"]}},
               "validated_bake": {"seconds": validated["total"], "cpu_seconds": validated["cpu_seconds"],
                                  "validation_seconds": v["seconds"],
                                  "validation_stages": v["stages"], "validated": v["validated"],
                                  "chosen": v["chosen"], "reason": v["reason"],
                                  "peak_rss_mb": validated["peak_rss_mb"]}}
    limits = machine_limits(work_dir, device, log)
    results["limits"] = limits
    results["memory_copy_rate_gbs"] = limits["copy_gbs"]["wall"]

    # ---- OpenCL
    results["replay_opencl"] = _bench_opencl(model, head, R, t, work_dir, repeats, chunk, device, limits, K_used,
                                             log)

    # ---- NumPy reference
    nf = min(numpy_frames, T)
    ev = NumpyEvaluator(model)
    ev.evaluate(head[:1])
    ev.stage_seconds = dict.fromkeys(ev.stage_seconds, 0.0)
    sink_out = np.empty((nf, V, 3), dtype=np.float32)

    def numpy_all():
        stream_chunks(ev, head[:nf], lambda s, f, l, n: sink_out.__setitem__(slice(s, s + len(f)), f), R[:nf],
                      t[:nf], chunk=chunk)

    t_numpy = median_time(numpy_all, repeats)
    stages = {k: v / repeats / nf * 1e3 for k, v in ev.stage_seconds.items()}
    stages["output"] = max(0.0, t_numpy / nf * 1e3 - sum(stages.values()))
    results["replay_numpy"] = {"frames": nf, "frames_per_second": nf / t_numpy, "ms_per_frame": t_numpy / nf * 1e3,
                               "stage_ms_per_frame": stages}
    log(f"numpy replay: {nf / t_numpy:.2f} frames/s ({t_numpy / nf * 1e3:.0f} ms/frame)")

    # ---- baseline the paper replaced: factor once, back-substitute every frame
    results["baseline_sparse_solve"] = _bench_baseline(model, head[:min(baseline_frames, T)], repeats, log)
    ocl = results["replay_opencl"]
    base = results["baseline_sparse_solve"]
    results["ratios"] = {
        "opencl_in_memory_vs_sparse_solve": ocl["in_memory"]["frames_per_second"] / base["frames_per_second"],
        "opencl_writing_vs_sparse_solve": ocl["writing_positions"]["frames_per_second"] / base["frames_per_second"],
        "opencl_in_memory_vs_numpy": ocl["in_memory"]["frames_per_second"]
        / results["replay_numpy"]["frames_per_second"],
        "paper_ms_per_frame": 17.0,
        "opencl_in_memory_ms_per_frame": ocl["in_memory"]["ms_per_frame"],
    }
    import pyopencl

    results["machine"] = {"cpu": _cpu_name(), "cores": os.cpu_count(), "python": platform.python_version(),
                          "numpy": np.__version__, "pyopencl": pyopencl.VERSION_TEXT,
                          "load_average_start": load_start, "load_average_end": _load(),
                          "bench_peak_rss_mb": _peak_rss_mb(),
                          # malloc's huge pages, as the command line sets them up (facepipe.cli.large_pages)
                          "large_pages": "glibc.malloc.hugetlb" in os.environ.get("GLIBC_TUNABLES", "")}
    # ---- exports: sizes and MB/s per format, OBJ against trimesh, on the ICT mesh when
    # ../shared is there, else on this rig's
    from bench.export_speed import run_export_bench

    results["export"] = run_export_bench(work_dir / "export", mesh_path=rig_dir / "neutral.obj", repeats=repeats,
                                         resolution=exr_resolution, prefer_ict=use_kit, log=log)
    # ---- lifting a 2D landmark take (68 landmarks, 26 examples): on the ICT kit's video take when
    # ../shared is there, else on the sample rig filmed by a synthetic camera
    from bench.video_lift import lift_speed

    results["video_lift"] = lift_speed(work_dir / "video", repeats=max(repeats, 3), use_kit=use_kit, log=log)
    return results


def _timed(fn, repeats: int) -> tuple[float, float]:
    """(median wall seconds, least busy seconds) of ``repeats`` calls of ``fn()``; busy: this
    process's CPU seconds ÷ the machine's cores — the time the run would take were the cores
    its own and always busy (a bound: it does not count what waits on what)."""
    walls, busy = [], float("inf")
    cores = os.cpu_count() or 1
    for _ in range(repeats):
        r0, t0 = resource.getrusage(resource.RUSAGE_SELF), time.perf_counter()
        fn()
        walls.append(time.perf_counter() - t0)
        r1 = resource.getrusage(resource.RUSAGE_SELF)
        busy = min(busy, (r1.ru_utime + r1.ru_stime - r0.ru_utime - r0.ru_stime) / cores)
    return statistics.median(walls), busy


def _rates(T: int, wall: float, busy: float) -> dict:
    return {"frames_per_second": T / wall, "ms_per_frame": wall / T * 1e3,
            "busy_frames_per_second": T / busy if busy > 0 else None}


def _bench_opencl(model, head, R, t, work_dir: Path, repeats: int, chunk: int, device, limits: dict,
                  K_used: float, log) -> dict:
    from facepipe.opencl import OpenCLEvaluator
    from facepipe.pipeline.replay import replay

    T, V = head.shape[0], model.n_vertices
    t0 = time.perf_counter()
    ev = OpenCLEvaluator(model, device=device, chunk=chunk)
    # the destination is touched once before timing: a fresh array costs a page fault per 4 KB
    # on first write (~8 ms per 530k-vertex frame in this VM), an allocation cost, not replay's
    out = np.zeros((T, V, 3), dtype=np.float32)
    out.fill(0.0)

    def keep(s, f, l, n):
        out[s:s + f.shape[0]] = f

    ev.stream(head[:chunk], keep, R[:chunk], t[:chunk])  # first launch: the kernels are compiled for this shape
    setup = time.perf_counter() - t0
    log(f"opencl: {ev.device}; {ev.vw} frames per vector; setup {setup:.1f} s")

    in_place = []
    ev.stream(head[:chunk], lambda s, f, l, n: in_place.append(f.ctypes.data == out[s:].ctypes.data),
              R[:chunk], t[:chunk], destination=out[:chunk])
    in_place = bool(in_place) and all(in_place)
    ev.stage_seconds = dict.fromkeys(ev.stage_seconds, 0.0)
    t_mem, b_mem = _timed(lambda: ev.stream(head, lambda *a: None, R, t, destination=out), repeats)
    device_stages = {k: v / repeats / T * 1e3 for k, v in ev.stage_seconds.items()}
    log(f"opencl replay, positions kept in memory: {T / t_mem:.1f} frames/s ({t_mem / T * 1e3:.2f} ms/frame; "
        f"busy clock {T / b_mem:.1f} frames/s; "
        + ("written in place by the kernels)" if in_place else "copied out of device memory)"))
    t_copy, b_copy = _timed(lambda: ev.stream(head, keep, R, t), repeats)
    log(f"  the same, copied out of device memory by the sink: {T / t_copy:.1f} frames/s "
        f"({t_copy / T * 1e3:.2f} ms/frame; busy clock {T / b_copy:.1f} frames/s)")

    frames = np.arange(T)
    times = frames / 30.0

    def write():
        replay(model, head, R, t, frames, times, work_dir / "replay_opencl", evaluator=ev, chunk=chunk)

    t_write, b_write = _timed(write, repeats)
    log(f"opencl replay, writing positions.npy: {T / t_write:.1f} frames/s ({t_write / T * 1e3:.2f} ms/frame; "
        f"busy clock {T / b_write:.1f} frames/s)")

    # before this session's changes, in the same run: 8-frame vectors, positions copied out of
    # device memory (in memory), and copied into the writer's buffer (written)
    old_ev = OpenCLEvaluator(model, device=device, chunk=chunk, vector_width=8)
    old_ev.takes_placement = False
    old_ev.stream(head[:chunk], keep, R[:chunk], t[:chunk])
    t_old_mem, b_old_mem = _timed(lambda: old_ev.stream(head, keep, R, t), repeats)
    t_old_write, b_old_write = _timed(lambda: replay(model, head, R, t, frames, times, work_dir / "replay_opencl",
                                                     evaluator=old_ev, chunk=chunk), repeats)
    log(f"  before (8-frame vectors, copies): {T / t_old_mem:.1f} frames/s in memory (busy clock "
        f"{T / b_old_mem:.1f}), {T / t_old_write:.1f} writing positions.npy (busy clock {T / b_old_write:.1f})")

    tables = _roofline_tables(model, head, R, t, work_dir, repeats, chunk, device, limits, K_used, ev, in_place,
                              log)
    return {"device": ev.device, "setup_seconds": setup, "vector_width": ev.vw,
            "in_memory": dict(_rates(T, t_mem, b_mem), written_in_place=in_place),
            "in_memory_copied_by_sink": _rates(T, t_copy, b_copy),
            "writing_positions": _rates(T, t_write, b_write),
            "before": {"vector_width": 8, "in_memory": _rates(T, t_old_mem, b_old_mem),
                       "writing_positions": _rates(T, t_old_write, b_old_write)},
            "pipeline_device_ms_per_frame": device_stages, "roofline": tables}


def _roofline_tables(model, head, R, t, work_dir: Path, repeats: int, chunk: int, device, limits: dict,
                     K_used: float, ev, in_place: bool, log) -> dict:
    """The per-stage roofline tables, before (8-frame vectors, positions copied out of device
    memory, and copied again into the writer's buffer) and after (the device's widest vectors,
    positions written in place: into the caller's array, or into the writer's memory), by both
    clocks."""
    from bench.replay_stages import measure_stages
    from bench.roofline import format_table, stage_flops, stage_table

    V, H = model.n_vertices, int(len(model.handle_vertices))
    P = int(model.basis_features.shape[0])
    ring = 3.0 * len(model.triangles) / V
    fan_entries = ev.fan_entries / V
    flops = stage_flops(V, H, P, K_used, ring, model.method, fans=fan_entries - ring)
    tables = {}
    for name, width in (("before", 8), ("after", None)):
        m = measure_stages(model, head, R, t, work_dir, device=device, chunk=chunk, vector_width=width,
                           repeats=repeats, placed=name == "after")
        nbytes = stage_bytes(V, H, P, K_used, chunk, model.method, fan_entries)
        nbytes.update(host_tables=0.0, host_copy=2 * V * 3 * 4.0, positions_write=V * 3 * 4.0)
        entry = {"vector_width": m["vector_width"], "threads": m["threads"],
                 "fused_kernel_ms_per_frame": {k: m[k]["fused_kernel"] for k in ("wall", "busy")}}
        for clock in ("busy", "wall"):
            stage_ms = {k: v for k, v in m[clock].items() if k != "fused_kernel"}
            if name == "after" and in_place:
                stage_ms["host_copy"] = 0.0  # the kernels write the caller's array themselves
            entry[clock] = stage_table(stage_ms, flops, nbytes, limits["fma_gflops"][clock],
                                       limits["copy_gbs"][clock], limits.get("disk_write_gbs"),
                                       limits["device_copy_gbs"][clock])
        tables[name] = entry
        busy = "a GPU's kernels by their own time, host stages by CPU time" if m["gpu"] else \
            f"CPU time ÷ {m['threads']} device threads"
        log(format_table(entry["busy"], f"replay stages, {name} ({m['vector_width']}-frame vectors; busy clock: "
                                        f"{busy}; least of {repeats})"))
        log(format_table(entry["wall"], f"replay stages, {name} (wall clock)"))
        log(f"  (frames, fine_scale and output are one fused kernel, split by building it without one or both: "
            f"the whole kernel {m['busy']['fused_kernel']:.3f} ms/frame busy, {m['wall']['fused_kernel']:.3f} wall)")
    return tables


def _bench_baseline(model, head, repeats: int, log) -> dict:
    """Large scale only, the way the paper's baseline does it: u = −A_ff⁻¹ A_fH u_H per frame."""
    import scipy.sparse as sp

    from facepipe.core.shell import CholeskyFactor, constrained_split, constrained_system, shell_operator

    rest = model.rest.astype(np.float64)
    hv = model.handle_vertices.astype(np.int64)
    shell = model.meta.get("shell", {"k_stretch": 0.0, "k_bend": 1.0})
    V = len(rest)
    A = shell_operator(rest, model.triangles.astype(np.int64), shell["k_stretch"], shell["k_bend"],
                       model.meta["marker_spacing"])
    _, constrained = constrained_split(V, hv, model.anchors)
    U, R = constrained_system(A, constrained, hv)
    del A
    R = sp.csr_matrix(R)  # −A_fH and the identity on the handle rows
    t0 = time.perf_counter()
    factor = CholeskyFactor(U, upper=True)  # dense right-hand sides: the whole factor read per frame
    t_factor = time.perf_counter() - t0
    u = head - rest[hv]
    out = np.empty((V, 3))

    def solve_all():
        for f in range(u.shape[0]):
            out[:] = factor.solve(np.asarray(R @ u[f]))

    t_solve = median_time(solve_all, repeats)
    n = u.shape[0]
    log(f"per-frame sparse solve ({factor.backend}, large scale only): {n / t_solve:.2f} frames/s "
        f"(factor once: {t_factor:.1f} s)")
    return {"backend": factor.backend, "frames": n, "factor_seconds": t_factor, "frames_per_second": n / t_solve,
            "ms_per_frame": t_solve / n * 1e3}


def _json_value(o):
    if isinstance(o, np.ndarray):
        return o.tolist()
    return o.item() if isinstance(o, np.generic) else str(o)


@click.command()
@click.option("-o", "--output", default="bench/results.json", show_default=True, type=click.Path(dir_okay=False))
@click.option("--vertices", default=20000, show_default=True, help="Vertices of the generated rig.")
@click.option("--frames", default=64, show_default=True)
@click.option("--repeats", default=3, show_default=True, help="Timings are medians over this many runs.")
@click.option("--bake-repeats", default=3, show_default=True,
              help="Bakes with the config's parameters timed (the median is reported); the validated bake runs once.")
@click.option("--work", default="bench/work", show_default=True, type=click.Path(file_okay=False))
@click.option("--markers", default=None, type=int, help="Markers driving the shell [default: the sample's 96].")
@click.option("--examples", default=6, show_default=True, help="Example poses of the generated rig.")
@click.option("--chunk", default=32, show_default=True, help="Frames per OpenCL launch.")
@click.option("--device", default=None, help="OpenCL device (as replay --device).")
@click.option("--kit/--no-kit", default=True, show_default=True,
              help="Exports and the 2D lift on the ICT kit in ../shared when it is there; --no-kit: on the generated rig alone.")
@click.option("--exr-resolution", default=2048, show_default=True, type=click.IntRange(min=16),
              help="EXR displacement maps' size per UDIM tile.")
@click.option("--quiet", "-q", is_flag=True, help="Print nothing but errors.")
def main(output, vertices, frames, repeats, bake_repeats, work, markers, examples, chunk, device, kit, exr_resolution,
         quiet):
    """Measure bake and replay speed on a generated rig; write the figures as JSON."""
    from facepipe.errors import InputError
    from facepipe.opencl.device import select_device

    say = (lambda text: None) if quiet else click.echo
    try:
        if device is not None:  # before the bake: a device that is not there is said at once, not minutes later
            select_device(device)
        results = run_bench(Path(work), n_vertices=vertices, n_frames=frames, repeats=repeats, chunk=chunk,
                            n_markers=markers, n_examples=examples, device=device, bake_repeats=bake_repeats,
                            use_kit=kit, exr_resolution=exr_resolution, log=say)
    except InputError as e:
        raise click.UsageError(str(e)) from None
    with atomic_path(Path(output)) as tmp:
        tmp.write_text(json.dumps(results, indent=2, default=_json_value))
    say(f"wrote {output}")


if __name__ == "__main__":
    from facepipe.cli.large_pages import restart_with_large_pages

    # started as `facepipe` starts (large pages for the heap where they help): the bake children
    # inherit it, and the replays measured here run as `facepipe replay` would
    restart_with_large_pages()
    main()
