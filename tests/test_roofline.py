"""The benchmark's rooflines (bench/roofline.py): the table's arithmetic, the FLOP counts, and the
FMA kernel doing the work it is credited with. No timing is asserted."""

import numpy as np
import pytest

from bench.roofline import _CHAINS, computed_fma_peak_gflops, fma_kernel, stage_flops, stage_table
from facepipe import opencl


def test_stage_table_takes_the_nearer_limit():
    # 2 GFLOP at 100 GFLOP/s = 20 ms; 0.1 GB at 10 GB/s = 10 ms: compute bound, limit 20 ms
    flops = {"a": 2e9, "b": 1e6, "c": 0.0}
    nbytes = {"a": 1e8, "b": 5e8, "c": 2e9}
    table = stage_table({"a": 30.0, "b": 100.0, "c": 2000.0}, flops, nbytes, peak_gflops=100.0, copy_gbs=10.0,
                        write_gbs=None)
    assert table["a"]["bound"] == "compute" and table["a"]["limit_ms_per_frame"] == pytest.approx(20.0)
    assert table["a"]["ratio_to_limit"] == pytest.approx(1.5)
    assert table["a"]["gflop_per_s"] == pytest.approx(2e9 / 0.03 / 1e9)
    assert table["b"]["bound"] == "memory" and table["b"]["limit_ms_per_frame"] == pytest.approx(50.0)
    assert table["c"]["ratio_to_limit"] == pytest.approx(10.0)


def test_positions_write_is_held_to_the_disk_rate():
    table = stage_table({"positions_write": 10.0}, {}, {"positions_write": 1e7}, 100.0, copy_gbs=10.0, write_gbs=1.0)
    assert table["positions_write"]["bound"] == "disk"
    assert table["positions_write"]["limit_ms_per_frame"] == pytest.approx(10.0)


def test_stage_flops_counts_the_large_scale_product():
    f = stage_flops(V=1000, H=89, P=7, K=16, ring=6.0, method="wpsd")
    assert f["large_scale"] == 1000 * 89 * 3 * 2  # one multiply-add per handle and coordinate
    assert f["fine_scale"] > stage_flops(1000, 89, 7, 8, 6.0, "wpsd")["fine_scale"] > 0
    assert stage_flops(1000, 89, 7, 16, 6.0, "none")["fine_scale"] == 0


def test_computed_peak_is_cores_times_lanes_times_clock():
    c = computed_fma_peak_gflops()
    assert c["gflops"] == pytest.approx(c["cores"] * 2 * c["float_lanes"] * 2 * c["mhz"] / 1e3)
    assert c["float_lanes"] in (4, 8, 16)


@pytest.mark.parametrize("width", [8, 16])
def test_fma_kernel_runs_every_iteration(width):
    """The kernel credited with 2·iterations FLOP per lane and chain computes x ← a·x + b that many
    times: its output matches the closed form, so nothing was optimised away."""
    if not opencl.opencl_available():
        pytest.skip("no OpenCL device")
    import pyopencl as cl

    from facepipe.opencl.device import open_device

    context, _ = open_device(None)
    queue = cl.CommandQueue(context)
    kernel = fma_kernel(context, width)
    items, n, a, b = 4, 37, 0.9, 0.25
    out = cl.Buffer(context, cl.mem_flags.WRITE_ONLY, size=4 * items)
    kernel(queue, (items,), None, out, np.int32(n), np.float32(a), np.float32(b))
    got = np.empty(items, np.float32)
    cl.enqueue_copy(queue, got, out)
    x0 = np.arange(items)[:, None] + np.arange(_CHAINS)[None, :]
    xn = x0 * a ** n + b * (1 - a ** n) / (1 - a)
    assert np.allclose(got, 2 * xn.sum(axis=1), rtol=1e-4)


def test_the_bench_refuses_a_device_that_is_not_there_before_it_bakes(tmp_path):
    """`python -m bench.paper_scale --device X` names the devices it found and exits 2 at once,
    not after the bake (minutes at the paper's scale)."""
    from click.testing import CliRunner

    from bench.paper_scale import main

    if not opencl.opencl_available():
        pytest.skip("no OpenCL device that compiles kernels")
    result = CliRunner().invoke(main, ["--work", str(tmp_path / "work"), "--device", "no-such-device-xyz",
                                       "-o", str(tmp_path / "r.json")])
    assert result.exit_code == 2
    assert "matches no OpenCL device" in result.output and "found:" in result.output
    assert not (tmp_path / "work").exists() and not (tmp_path / "r.json").exists()
