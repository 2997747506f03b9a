"""What each part of the fused replay kernel costs: the stage table (bench/replay_stages.py) for
variants of the kernel with one part taken out. Timing only: a variant's positions are wrong.

A stage's time in the table is a difference between builds of one kernel, so it also holds what
the stage costs the others running beside it on the same cores. Taking a part out and timing the
stages again says how much of a stage's time that part is, and where the rest goes (the fine
scale beside the output's scattered stores, say). Each variant is the kernel's own source with
text replaced; a replacement that no longer matches the source stops the run, naming it (the
kernel changed: the variant must be written again).

Needs the model and take that ``python -m bench.paper_scale`` leaves in its work folder
(``make bench``: bench/work/model.npz and bench/work/rig/take_truth.npz):

    python -m bench.kernel_variants --work bench/work --json bench/kernel_variants.json

Variants run in ``--rounds`` interleaved rounds; each figure is the least over the rounds (and
over each round's ``--repeats`` passes), the least disturbed by the host's other work.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import click
import numpy as np

#: the output's stores kept only where a lane is NaN (never): the positions are computed, not stored
_STORES = ("    store_point(out, fx, fy, fz, c0, n_frames, V, o);",
           "#if VW == 1\n    if (fx != fx)\n#else\n    if (fx.s0 != fx.s0)\n#endif\n"
           "        store_point(out, fx, fy, fz, c0, n_frames, V, o);")
#: the WPSD distances' test for a frame near a basis pose (and the recount it may start)
_NEAR = ("    if (any_near) {", "    if (0) {")
#: the distances' square roots: r² used as r
_SQRT = ("        r[i] = VSQRT(MAX(r[i], (vfloat)(0.0f)));", "        r[i] = MAX(r[i], (vfloat)(0.0f));")
#: the basis poses' features: a register in place of each load
_BASIS = ("            r[i] = FMA(af, (vfloat)(basis[i * F + e]), r[i]);", "            r[i] = FMA(af, f, r[i]);")
#: the frame's feature of each edge: the edge's weight in place of the load
_FEATURES = ("        const vfloat f = VLOAD(features + e * C + c0);\n        const vfloat af = a * f;",
             "        const vfloat f = (vfloat)(a);\n        const vfloat af = a * f;")
#: every vertex's edge loop run to K (the padding's weights are 0)
_TRIPS = ("    const int count = edge_count[v];", "    const int count = K;")

#: the frames' gathers: each fan neighbour's position made from its index instead of loaded, and
#: not prefetched (the cross products, sums and normalisations stay)
_FAN_LOADS = ("""        __global const float *pb = fan_row(pos, C, c0, j);
        const vfloat bx = VLOAD(pb) - px, by = VLOAD(pb + C) - py, bz = VLOAD(pb + 2 * C) - pz;""",
              """        const vfloat nb = (vfloat)((float)j);
        const vfloat bx = nb - px, by = nb + 1.0f - py, bz = nb + 2.0f - pz;""")
_PREFETCH = ("#if PREFETCH\n    if (w >= V)", "#if 0\n    if (w >= V)")

#: the frames' two normalisations without their square root and division (the products stay)
_NORMALISE = ("""    const vfloat len = VSQRT(*x * *x + *y * *y + *z * *z);
    const vfloat inv = 1.0f / SELECT((vfloat)(1.0f), len, len > 1e-30f);""",
              """    const vfloat len = *x * *x + *y * *y + *z * *z;
    const vfloat inv = SELECT((vfloat)(1.0f), len, len > 1e-30f);""")

VARIANTS: dict[str, tuple] = {
    "as built": (),
    "without the output's stores": (_STORES,),
    "without the near-pose test": (_NEAR,),
    "without the distances' square roots": (_SQRT,),
    "without the basis's loads": (_BASIS,),
    "without the features' loads": (_FEATURES,),
    "edge loop run to K": (_TRIPS,),
    "without the near-pose test and square roots": (_NEAR, _SQRT),
    "without the near-pose test, square roots and stores": (_NEAR, _SQRT, _STORES),
    "without the fans' neighbour loads": (_FAN_LOADS, _PREFETCH),
    "without the fans' neighbour loads and the stores": (_FAN_LOADS, _PREFETCH, _STORES),
    "without the normalisations' roots and divisions": (_NORMALISE,),
}


def variant_source(source: str, replacements: tuple, label: str = "") -> str:
    """``source`` with each (old, new) replaced; an ``old`` not in it exactly once is an error naming the variant."""
    for old, new in replacements:
        if source.count(old) != 1:
            raise ValueError(f"kernel variant {label!r}: {old.strip()!r} is in the kernel "
                             f"{source.count(old)} times, not once (the kernel changed; write the variant again)")
        source = source.replace(old, new)
    return source


def run_variants(work_dir: Path, labels: list[str], rounds: int = 2, repeats: int = 3, chunk: int = 32,
                 device=None, log=print) -> dict:
    """{"fine_scale_limit": {...}, "variants": {label: {"busy": {stage: ms a frame}, "wall": {...},
    "fine_scale_ratio_to_limit"}}}, each figure the least over ``rounds``."""
    import facepipe.opencl.device as opencl_device
    from bench.replay_stages import measure_stages
    from facepipe.io.model_file import load_model

    model = load_model(work_dir / "model.npz")
    truth = np.load(work_dir / "rig" / "take_truth.npz")["positions"]
    head = truth[:, model.handle_vertices].astype(np.float64)
    del truth
    T = head.shape[0]
    R = np.broadcast_to(np.eye(3), (T, 3, 3)).copy()
    t = np.zeros((T, 3))
    shipped = opencl_device.kernel_source
    sources = {label: variant_source(shipped("replay.cl"), VARIANTS[label], label) for label in labels}
    best: dict = {}
    limit = _fine_scale_limit(model, device)
    log(f"fine scale: {limit['gflop_per_frame']:.3f} GFLOP a frame, {limit['ms_per_frame']:.3f} ms a frame at the "
        f"FMA peak ({limit['fma_gflops']:.0f} GFLOP/s by CPU time)")
    try:
        for r in range(rounds):
            for label in labels:
                # the program cache keys on the source text, so each variant is compiled from its own
                opencl_device.kernel_source = (lambda name="replay.cl", text=sources[label]:
                                               text if name == "replay.cl" else shipped(name))
                t0 = time.perf_counter()
                m = measure_stages(model, head, R, t, work_dir, device=device, chunk=chunk, repeats=repeats)
                entry = best.setdefault(label, {"busy": {}, "wall": {}})
                for clock in ("busy", "wall"):
                    for stage, ms in m[clock].items():
                        entry[clock][stage] = min(entry[clock].get(stage, float("inf")), ms)
                log(f"round {r + 1}/{rounds} {label:52s} " + " ".join(
                    f"{s} {m['busy'][s]:.3f}" for s in ("frames", "fine_scale", "output", "fused_kernel"))
                    + f" ms ({time.perf_counter() - t0:.0f} s)")
    finally:
        opencl_device.kernel_source = shipped
    for entry in best.values():  # (a model without details has no fine scale to hold to a limit)
        entry["fine_scale_ratio_to_limit"] = (entry["busy"]["fine_scale"] / limit["ms_per_frame"]
                                              if limit["ms_per_frame"] > 0 else None)
    return {"fine_scale_limit": limit, "variants": best}


def _fine_scale_limit(model, device) -> dict:
    """The fine scale's FLOP a frame (bench/roofline.py's count) and its time at this run's FMA peak
    (busy clock), as the stage table of bench.paper_scale computes them."""
    from bench.roofline import opencl_fma_peak_gflops, stage_flops
    from facepipe.opencl.device import open_device

    context, dev = open_device(device)
    width = 1 if dev.type & 4 else (16 if dev.preferred_vector_width_float >= 16 else 8)
    peak = opencl_fma_peak_gflops(context, dev, max(width, 4))["busy"]
    P = int(model.basis_features.shape[0])
    K_used = float((model.edge_weight > 0).sum(axis=1).mean())
    # the ring size (6) enters only the frames' count
    flop = stage_flops(model.n_vertices, len(model.handle_vertices), P, K_used, 6.0, model.method)["fine_scale"]
    return {"gflop_per_frame": flop / 1e9, "fma_gflops": peak, "ms_per_frame": flop / (peak * 1e9) * 1e3}


@click.command()
@click.option("--work", default="bench/work", show_default=True, type=click.Path(file_okay=False, exists=True),
              help="bench.paper_scale's work folder (model.npz, rig/take_truth.npz).")
@click.option("--variant", "variants", multiple=True, type=click.Choice(list(VARIANTS)),
              help="A variant to time (repeatable) [default: all].")
@click.option("--rounds", default=2, show_default=True, type=click.IntRange(min=1))
@click.option("--repeats", default=3, show_default=True, type=click.IntRange(min=1))
@click.option("--device", default=None, help="OpenCL device (as replay --device).")
@click.option("--json", "json_path", default=None, type=click.Path(dir_okay=False), help="Write the figures here.")
@click.option("--quiet", "-q", is_flag=True)
def main(work, variants, rounds, repeats, device, json_path, quiet):
    """Time the replay kernel's stages with parts of the kernel taken out."""
    from facepipe.errors import InputError
    from facepipe.io.atomic import atomic_path
    from facepipe.opencl.device import select_device

    say = (lambda text: None) if quiet else click.echo
    labels = list(variants) or list(VARIANTS)
    missing = [name for name in ("model.npz", "rig/take_truth.npz") if not (Path(work) / name).is_file()]
    if missing:
        raise click.UsageError(f"{work} has no {' or '.join(missing)}: build the bench's model and take first "
                               f"(python -m bench.paper_scale --work {work}, as make bench does)")
    try:
        if device is not None:  # before the 530k model is read
            select_device(device)
        result = run_variants(Path(work), labels, rounds=rounds, repeats=repeats, device=device, log=say)
    except InputError as e:  # a device that is not there, a model file that is not one
        raise click.UsageError(str(e)) from None
    say("busy clock, ms a frame (least over the rounds); the fine scale ÷ its FMA limit:")
    for label, entry in result["variants"].items():
        say(f"  {label:52s} " + " ".join(f"{s} {entry['busy'][s]:.3f}"
                                         for s in ("frames", "fine_scale", "output", "fused_kernel"))
            + (f"  ({entry['fine_scale_ratio_to_limit']:.2f})" if entry["fine_scale_ratio_to_limit"] else ""))
    if json_path:
        with atomic_path(Path(json_path)) as tmp:
            tmp.write_text(json.dumps({"rounds": rounds, "repeats": repeats, **result}, indent=2))
        say(f"wrote {json_path}")


if __name__ == "__main__":
    main()
