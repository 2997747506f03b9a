"""bench/kernel_variants.py: each variant still matches the kernel's source, and a variant built in
the same process as the shipped kernel is compiled from its own text (the program cache keys on
the source). No timing is asserted."""

import numpy as np
import pytest

from bench.kernel_variants import VARIANTS, variant_source
from facepipe import opencl
from facepipe.io.model_file import model_from_fit
from facepipe.pipeline.fit import fit_rig
from facepipe.pipeline.replay import NumpyEvaluator
from facepipe.pipeline.rig import load_rig
from facepipe.sample_rig import write_sample_rig


def test_every_variant_matches_the_shipped_kernel_once():
    source = opencl.device.kernel_source("replay.cl")
    for label, replacements in VARIANTS.items():
        changed = variant_source(source, replacements, label)
        assert (changed == source) == (not replacements), label


def test_a_variant_the_kernel_outgrew_is_refused_by_name():
    with pytest.raises(ValueError, match="'gone'.*not once"):
        variant_source("__kernel void k() {}", (("x = 1;", "x = 2;"),), "gone")


def test_a_variant_is_compiled_from_its_own_text(tmp_path, monkeypatch):
    """The shipped kernel matches the NumPy reference; the variant without the output's stores,
    built next in the same process, leaves the caller's array as it was."""
    if not opencl.opencl_available():
        pytest.skip("no OpenCL device that compiles kernels")
    write_sample_rig(tmp_path / "rig", n_vertices=3000, n_examples=4, n_frames=8)
    rig = load_rig(tmp_path / "rig" / "sample.toml")
    model = model_from_fit(fit_rig(rig), rig, "wpsd")
    head = np.load(tmp_path / "rig" / "take_truth.npz")["positions"][:, rig.handles].astype(np.float64)
    reference = NumpyEvaluator(model).evaluate(head)
    out = np.full(reference.shape, np.nan, np.float32)
    opencl.OpenCLEvaluator(model, chunk=8).evaluate(head, out=out)
    assert np.allclose(out, reference, atol=1e-4 * float(np.ptp(reference)))

    shipped = opencl.device.kernel_source("replay.cl")
    text = variant_source(shipped, VARIANTS["without the output's stores"])
    monkeypatch.setattr(opencl.device, "kernel_source", lambda name="replay.cl": text)
    out[:] = np.nan
    opencl.OpenCLEvaluator(model, chunk=8).evaluate(head, out=out)
    assert not np.isfinite(out).any() or not np.allclose(out, reference, atol=1e-4 * float(np.ptp(reference)))


def test_a_work_folder_without_the_benchs_model_is_refused_by_name(tmp_path):
    from click.testing import CliRunner

    from bench.kernel_variants import main

    result = CliRunner().invoke(main, ["--work", str(tmp_path)])
    assert result.exit_code == 2
    assert "no model.npz or rig/take_truth.npz" in result.output and "bench.paper_scale" in result.output


def test_a_device_that_is_not_there_and_a_model_that_is_not_one_are_refused_by_name(tmp_path):
    from click.testing import CliRunner

    from bench.kernel_variants import main

    if not opencl.opencl_available():
        pytest.skip("no OpenCL device that compiles kernels")
    (tmp_path / "rig").mkdir()
    (tmp_path / "model.npz").write_bytes(b"")
    (tmp_path / "rig" / "take_truth.npz").write_bytes(b"")
    result = CliRunner().invoke(main, ["--work", str(tmp_path), "--device", "no-such-device-xyz"])
    assert result.exit_code == 2 and "matches no OpenCL device" in result.output
    result = CliRunner().invoke(main, ["--work", str(tmp_path)])
    assert result.exit_code == 2 and "model.npz" in result.output and "it is empty" in result.output
