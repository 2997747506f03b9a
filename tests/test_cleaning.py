"""Cleaning through the rig's prior and the prepare_take pipeline, against synthetic truth.

A synthetic rig (markers on a face-sized patch, a few example expressions) and takes made
from it with known head motion, weights, gaps, noise and jumps: the independent check is
the truth the take was made from. The ICT kit's noisy take checks the issue's acceptance
figures end to end (skipped when ../shared is absent).
"""

from __future__ import annotations

import json
import re
from types import SimpleNamespace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from facepipe.core.rigid import rotation_from_vector
from facepipe.mocap.cleaning import CleanOptions, clean_take
from facepipe.mocap.outliers import find_jumps, noise_sigma
from facepipe.mocap.pose_expression import fit_pose_expression
from facepipe.errors import InputError
from facepipe.mocap import Take
from facepipe.mocap.prepare import PrepareOptions, prepare_take, summary_lines
from tests.conftest import run_cli

H, K, T = 30, 5, 80


def make_rig(seed=0):
    rng = np.random.default_rng(seed)
    theta = rng.uniform(-1.0, 1.0, H)
    phi = rng.uniform(-0.8, 0.8, H)
    rest = 8.0 * np.stack([np.sin(theta) * np.cos(phi), np.sin(phi), np.cos(theta) * np.cos(phi)], axis=1)
    stable = np.zeros(H, bool)
    stable[-6:] = True
    centres = rng.normal(scale=4.0, size=(K, 3))
    basis = np.stack([0.8 * np.exp(-np.sum((rest - c) ** 2, 1) / 20.0)[:, None] * rng.normal(size=3) for c in centres])
    basis[:, stable] *= 0.1  # stable skin moves a little with expressions
    names = [f"M{i:02d}" for i in range(H - 6)] + [f"S{i}" for i in range(6)]
    model = SimpleNamespace(rest=rest, handle_vertices=np.arange(H), stable=stable,
                            example_handles=np.concatenate([rest[None], rest + basis]),
                            meta={"marker_spacing": 2.0, "units": "cm"}, marker_names=names)
    return model, rest, basis, stable, names


def make_truth(rest, basis, seed=1, degrees=15.0):
    rng = np.random.default_rng(seed)
    s = np.linspace(0, 1, T)
    weights = np.clip(np.stack([np.sin(np.pi * (s * (k + 1) + rng.uniform())) for k in range(K)], 1), 0, None)
    head = rest + np.einsum("tk,khc->thc", weights, basis)
    rotvec = np.radians(degrees) * np.stack([np.sin(3 * s), 0.5 * np.sin(2 * s + 1), 0.3 * s], 1)
    R = Rotation.from_rotvec(rotvec).as_matrix()
    t = np.stack([2 * s, np.sin(4 * s), -s], 1) + [0.0, 150.0, 10.0]
    world = np.einsum("tij,thj->thi", R, head) + t[:, None, :]
    return world, head, R, t, weights


def take_of(world, names, units="cm") -> Take:
    frames = np.arange(len(world), dtype=np.int64)
    return Take(frames=frames, times=frames / 30.0, positions=world.copy(), marker_names=list(names), units=units,
                source_units=units, fps=30.0, format="c3d", path="synthetic.c3d")


# --------------------------------------------------------------------------- pieces


def test_rotation_from_vector_matches_scipy():
    v = np.random.default_rng(0).normal(size=(20, 3))
    v[0] = 0.0
    v[1] = 1e-10
    np.testing.assert_allclose(rotation_from_vector(v), Rotation.from_rotvec(v).as_matrix(), atol=1e-12)


def test_fit_pose_expression_is_exact_in_the_span():
    _, rest, basis, _, _ = make_rig()
    world, head, R, t, weights = make_truth(rest, basis)
    R0 = np.tile(np.eye(3), (T, 1, 1))
    t0 = world.mean(axis=1) - rest.mean(axis=0)
    R2, t2, C, _ = fit_pose_expression(world, np.ones((T, H)), rest, basis, R0, t0, iterations=25)
    np.testing.assert_allclose(R2, R, atol=1e-8)
    np.testing.assert_allclose(t2, t, atol=1e-6)
    np.testing.assert_allclose(C, weights, atol=1e-7)  # zeros stay exact zeros: non-negative weights
    assert (C >= 0).all()


def test_fit_pose_expression_stops_each_frame_on_its_own(monkeypatch):
    """Each frame iterates until its step is below CONVERGED_STEP: a frame gets the same fit in a
    batch as alone, a converged frame stops (frames already at their fit take one step), and the
    result is what all the iterations would give (to round-off)."""
    from facepipe.mocap import pose_expression

    _, rest, basis, _, _ = make_rig()
    world, head, R, t, weights = make_truth(rest, basis)
    world = world + np.random.default_rng(3).normal(scale=0.02, size=world.shape)  # not exactly in the span
    R0 = np.tile(np.eye(3), (T, 1, 1))
    t0 = world.mean(axis=1) - rest.mean(axis=0)
    args = (np.ones((T, H)), rest, basis)
    together = fit_pose_expression(world, *args, R0, t0, iterations=25, robust_scale=0.05)
    alone = [fit_pose_expression(world[f:f + 1], args[0][f:f + 1], rest, basis, R0[f:f + 1], t0[f:f + 1],
                                 iterations=25, robust_scale=0.05) for f in range(0, T, 7)]
    for i, f in enumerate(range(0, T, 7)):
        for a, b in zip(together, alone[i]):
            np.testing.assert_allclose(a[f], b[0], rtol=0, atol=1e-12)
    # frames already at their fit stop after one step
    steps = []
    original = pose_expression._normal_equations
    monkeypatch.setattr(pose_expression, "_normal_equations", lambda R, y, *rest_: steps.append(len(y)) or original(R, y, *rest_))
    again = fit_pose_expression(world, *args, together[0], together[1], together[2], iterations=25, robust_scale=0.05)
    assert steps[0] == T and sum(steps) < 3 * T
    for a, b in zip(together, again):
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-9)
    # without the stop every frame takes every iteration: the same fit
    monkeypatch.setattr(pose_expression, "CONVERGED_STEP", -1.0)
    steps.clear()
    every = fit_pose_expression(world, *args, R0, t0, iterations=25, robust_scale=0.05)
    assert sum(steps) == 25 * T
    for a, b in zip(together, every):
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-9)


def test_noise_sigma_of_white_noise_on_smooth_motion():
    rng = np.random.default_rng(5)
    s = np.linspace(0, 4, 400)[:, None, None]
    smooth = 0.3 * np.sin(s + rng.uniform(size=(1, 20, 3)))
    noise = rng.normal(scale=0.02, size=(400, 20, 3))
    vis = rng.random((400, 20)) > 0.1
    assert noise_sigma(smooth + noise, vis) == pytest.approx(0.02, rel=0.1)
    assert noise_sigma(smooth, vis) < 1e-4


def test_find_jumps_spikes_plateaus_and_edges_but_not_fast_motion():
    rng = np.random.default_rng(4)
    r = rng.normal(scale=0.01, size=(60, 4, 3))
    known = np.ones((60, 4), bool)
    r[10, 0] += [0.3, 0.0, 0.0]  # spike
    r[20:28, 1] += [0.0, 0.4, 0.0]  # knocked loose for 8 frames
    r[0, 2] += [0.0, 0.0, 0.5]  # a bad first sample
    r[30:36, 3] += np.linspace(0, 1.0, 8)[1:-1, None] * [1.0, 0.0, 0.0]  # fast but continuous (a blink)
    r[36:40, 3] += [1.0, 0.0, 0.0]
    r[40:44, 3] += np.linspace(1.0, 0.0, 6)[1:-1, None] * [1.0, 0.0, 0.0]
    out = find_jumps(r, known, floor=0.1)
    assert np.flatnonzero(out[:, 0]).tolist() == [10]
    assert np.flatnonzero(out[:, 1]).tolist() == list(range(20, 28))
    assert np.flatnonzero(out[:, 2]).tolist() == [0]
    assert not out[:, 3].any()
    assert not find_jumps(r, known, floor=1.0).any()  # below the absolute floor
    assert not find_jumps(r[:2], known[:2], floor=0.1).any()


# --------------------------------------------------------------------------- clean_take


def test_prior_fills_long_gaps_exactly_when_the_truth_is_in_its_span():
    _, rest, basis, stable, names = make_rig()
    world, head, R, t, _ = make_truth(rest, basis)
    world[10:50, 3] = np.nan  # 40 frames
    world[:30, 7] = np.nan  # from the start
    world[60:, [1, 2, 4]] = np.nan  # to the end
    world[20:24, :12] = np.nan  # many at once
    res = clean_take(world, rest, basis, stable, np.arange(T) / 30.0, CleanOptions(), spacing=2.0, names=names)
    np.testing.assert_allclose(res.head, head, atol=1e-6)
    np.testing.assert_allclose(res.R, R, atol=1e-7)
    tot = res.report["total"]
    assert tot["missing"] == 40 + 30 + 60 + 48 - 8 and tot["outliers"] == 0
    assert res.report["markers"]["M03"]["longest_gap"] == 40 and res.report["markers"]["M03"]["from_prior"] == 40
    json.dumps(res.report)


def test_noise_is_reduced_below_the_markers_own():
    _, rest, basis, stable, names = make_rig()
    world, head, R, t, _ = make_truth(rest, basis)
    noisy = world + np.random.default_rng(2).normal(scale=0.02, size=world.shape)
    res = clean_take(noisy, rest, basis, stable, np.arange(T) / 30.0, spacing=2.0)
    raw = np.einsum("tji,thj->thi", R, noisy - t[:, None, :])
    err_raw = np.sqrt(np.mean((raw - head) ** 2))
    err = np.sqrt(np.mean((res.head - head) ** 2))
    assert err < 0.5 * err_raw
    assert res.report["noise"]["sigma"] == pytest.approx(0.02, rel=0.2)
    from scipy.ndimage import gaussian_filter1d

    smooth = clean_take(noisy, rest, basis, stable, np.arange(T) / 30.0, CleanOptions(smooth=1.5), spacing=2.0)
    np.testing.assert_allclose(smooth.head, gaussian_filter1d(res.head, 1.5, axis=0, mode="nearest"), atol=1e-12)
    jitter = [np.sqrt(np.mean(np.diff(h, 2, axis=0) ** 2)) for h in (res.head, smooth.head)]
    assert jitter[1] < 0.8 * jitter[0] and smooth.report["smooth_frames"] == 1.5


def test_jumps_are_outliers_and_filled():
    _, rest, basis, stable, names = make_rig()
    world, head, R, t, _ = make_truth(rest, basis)
    bad = world.copy()
    bad[30, 5] += [1.0, -0.5, 0.5]  # a one-frame jump
    bad[40:52, 9] += [0.0, 0.6, 0.0]  # a marker knocked loose for 12 frames
    bad[55, -1] += [0.8, 0.0, 0.0]  # a stable marker jumps
    res = clean_take(bad, rest, basis, stable, np.arange(T) / 30.0, spacing=2.0, names=names)
    assert res.report["markers"]["M05"]["outliers"] == 1
    assert res.report["markers"]["M09"]["outliers"] == 12
    assert res.report["markers"]["S5"]["outliers"] == 1
    assert res.report["total"]["outliers"] == 14
    np.testing.assert_allclose(res.head, head, atol=1e-6)
    np.testing.assert_allclose(res.R, R, atol=1e-7)


def test_without_a_prior_long_gaps_decay_to_neutral():
    _, rest, basis, stable, names = make_rig()
    world, head, R, t, _ = make_truth(rest, basis, degrees=0.0)
    world[5:75, 2] = np.nan
    res = clean_take(world, rest, basis, stable, np.arange(T) / 30.0, CleanOptions(prior=False), spacing=2.0)
    # far from any sample of the marker the fill has faded to its rest position (35 frames
    # from a sample, e^(-35 / 6) of the residual is left)
    np.testing.assert_allclose(res.head[40, 2], rest[2], atol=0.01 * np.abs(head[:, 2] - rest[2]).max())
    # next to a sample it continues the marker smoothly
    assert np.linalg.norm(res.head[5, 2] - head[4, 2]) < np.linalg.norm(head[4, 2] - rest[2])


def test_frames_without_markers_are_interpolated():
    _, rest, basis, stable, names = make_rig()
    world, head, R, t, _ = make_truth(rest, basis)
    world[30:33] = np.nan
    world[50, :28] = np.nan  # 2 visible: no pose
    res = clean_take(world, rest, basis, stable, np.arange(T) / 30.0, spacing=2.0)
    assert res.report["total"]["frames_interpolated"] == 4
    assert np.isfinite(res.head).all() and np.isfinite(res.R).all()
    np.testing.assert_allclose(res.head[31], head[31], atol=0.1)  # smooth motion: close
    np.testing.assert_allclose(res.head[:30], head[:30], atol=1e-6)


# --------------------------------------------------------------------------- prepare_take


def test_prepare_detects_a_unit_mismatch():
    model, rest, basis, _, names = make_rig()
    world, *_ = make_truth(rest, basis)
    take = take_of(world * 10.0, names)  # mm numbers read as cm
    take.format, take.units, take.source_units = "facepipe-csv", "cm", "cm"
    with pytest.raises(InputError, match=r"unit mismatch.*in mm, not in cm.*\n  hint: pass --take-units mm"):
        prepare_take(take, model)
    with pytest.raises(InputError, match="seems to be in mm"):
        prepare_take(take, model, PrepareOptions(neutral_frame=0))
    take.positions = world * 1.8
    with pytest.raises(InputError, match="no unit explains it"):
        prepare_take(take, model)


@pytest.mark.parametrize("offset", [0.0, 0.1])
def test_prepare_with_a_neutral_frame_removes_offsets_and_aligns(offset):
    model, rest, basis, _, names = make_rig()
    world, head, R, t, _ = make_truth(rest, basis)
    offsets = np.random.default_rng(7).normal(scale=offset, size=(H, 3))  # the actor's markers vs the rig's
    A = Rotation.from_rotvec([0.0, 0.0, np.pi / 2]).as_matrix()  # capture space: another up axis
    actor = np.einsum("tij,thj->thi", R, head + offsets) + t[:, None, :]
    neutral = np.einsum("ij,hj->hi", R[0], rest + offsets) + t[0]
    takeworld = np.concatenate([neutral[None], actor]) @ A.T * 1.05 + [5.0, 0, 0]
    out, R2, t2, report = prepare_take(take_of(takeworld, names), model,
                                       PrepareOptions(neutral_frame=0, frames=slice(1, None)))
    # misplaced markers bias the neutral's scale a little (scale and offsets are not separable)
    tol = 1e-9 if offset == 0 else 5e-3
    assert report["alignment"]["scale"] == pytest.approx(1 / 1.05, rel=tol)
    assert report["alignment"]["offsets_rms"] == pytest.approx(np.sqrt(np.mean(np.sum(offsets**2, 1))), abs=0.01)
    np.testing.assert_allclose(out, head, atol=1e-6 if offset == 0 else 2e-3)
    # the head motion maps the rig to where the take's face is (rigid, rig scale)
    centre = rest.mean(axis=0)
    placed = np.einsum("tij,j->ti", R2, centre) + t2
    np.testing.assert_allclose(placed, (np.einsum("tij,j->ti", R, centre) + t) @ A.T * 1.05 + [5.0, 0, 0],
                               atol=1e-6 if offset == 0 else 0.05)
    np.testing.assert_allclose(np.linalg.det(R2), 1.0)


def test_prepare_with_a_neutral_take():
    model, rest, basis, _, names = make_rig()
    world, head, R, t, _ = make_truth(rest, basis)
    offsets = np.zeros((H, 3))
    offsets[:3] = [0.0, 0.2, 0.0]  # three markers sit higher on the actor
    actor = np.einsum("tij,thj->thi", R, head + offsets) + t[:, None, :]
    still = np.repeat((rest + offsets)[None], 5, 0) + [3.0, 1.0, 0.0]
    still[2, 4] = np.nan
    out, *_, rep = prepare_take(take_of(actor, names), model, PrepareOptions(neutral_take=take_of(still, names)))
    np.testing.assert_allclose(out, head, atol=2e-3)
    assert rep["alignment"]["offsets_max"] == pytest.approx(0.2, abs=0.02)
    with pytest.raises(InputError, match="neutral frame 500 is not in the take"):
        prepare_take(take_of(actor, names), model, PrepareOptions(neutral_frame=500))


def test_prepare_with_a_neutral_take_missing_a_marker_in_its_first_frame():
    # the neutral take's frames are aligned to its first usable frame: a marker missing there
    # is left out of that fit (it once made the SVD fail on NaN)
    model, rest, basis, _, names = make_rig()
    world, head, R, t, _ = make_truth(rest, basis)
    still = np.repeat(rest[None], 5, 0) + [3.0, 1.0, 0.0]
    still[0, 4] = np.nan
    out, *_, rep = prepare_take(take_of(world, names), model, PrepareOptions(neutral_take=take_of(still, names)))
    np.testing.assert_allclose(out, head, atol=2e-3)
    assert rep["alignment"]["offsets_max"] < 0.02


def test_replay_with_a_neutral_take_missing_a_marker_in_its_first_frame(tmp_path):
    assert run_cli("sample", tmp_path / "rig", "--vertices", 2000, "--frames", 24, "-q") == 0
    assert run_cli("bake", tmp_path / "rig" / "sample.toml", "-o", tmp_path / "model.npz", "-q") == 0
    header, first, *rest = (tmp_path / "rig" / "take.csv").read_text().splitlines()
    cells = first.split(",")
    cells[2:5] = ["", "", ""]  # the first marker's x, y, z
    neutral = tmp_path / "neutral.csv"
    neutral.write_text("\n".join([header, ",".join(cells), *rest]) + "\n")
    assert run_cli("replay", tmp_path / "rig" / "take.csv", "-m", tmp_path / "model.npz", "-o", tmp_path / "out",
                   "--backend", "numpy", "--neutral-take", neutral, "-q") == 0
    assert np.isfinite(np.load(tmp_path / "out" / "positions.npy")).all()


def test_prepare_switches_and_report():
    model, rest, basis, _, names = make_rig()
    world, head, R, t, _ = make_truth(rest, basis)
    world[10:20, 4] = np.nan
    take = take_of(world, names)
    full, *_ = prepare_take(take, model)
    part, Rp, _, rep = prepare_take(take, model, PrepareOptions(frames=slice(20, 30)))
    np.testing.assert_array_equal(part, full[20:30])  # a part replays as in the whole take
    lines = summary_lines(rep)
    assert any("10 missing samples" in ln for ln in lines) and json.dumps(rep)
    # --no-clean: pose from the stable markers, PCHIP gaps; the stable markers' own motion costs accuracy
    nc, Rn, _, rep_nc = prepare_take(take, model, PrepareOptions(clean=False))
    assert np.isfinite(nc).all() and rep_nc["total"]["filled"] == 10 and not rep_nc["cleaning"]["enabled"]
    assert np.abs(nc - head).max() > 1e-4
    # --no-stabilise: the take is taken as head space
    hs, Rs, ts, _ = prepare_take(take_of(head, names), model, PrepareOptions(stabilise=False))
    np.testing.assert_allclose(hs, head, atol=1e-6)
    np.testing.assert_array_equal(Rs, np.tile(np.eye(3), (T, 1, 1)))


def test_prepare_fallbacks_are_reported():
    model, rest, basis, stable, names = make_rig()
    world, head, R, t, _ = make_truth(rest, basis)
    # no stable markers in the rig: the pose comes from all markers through the prior
    model.stable = np.zeros(H, bool)
    out, R2, _, rep = prepare_take(take_of(world, names), model)
    np.testing.assert_allclose(out, head, atol=1e-6)
    assert any("fewer than 3 stable markers in the rig" in n for n in rep["notes"])
    model.stable = stable
    # an absent marker (NaN everywhere) is filled from the others through the prior, and said so
    take = take_of(world, names)
    take.positions[:, 3] = np.nan
    take.markers = {"absent": [names[3]]}
    out, *_, rep = prepare_take(take, model)
    np.testing.assert_allclose(out[:, 3], head[:, 3], atol=1e-6)
    assert rep["markers"][names[3]]["absent"] and any("absent from the take" in n for n in rep["notes"])
    with pytest.raises(InputError, match="never visible"):
        prepare_take(take, model, PrepareOptions(clean=False))
    take.positions[:] = np.nan
    with pytest.raises(InputError, match="no marker is visible"):
        prepare_take(take, model)


# --------------------------------------------------------------------------- the ICT kit


@pytest.fixture(scope="module")
def ict_model(ict_rig_fit):
    from facepipe.io.model_file import model_from_fit

    rig, fit = ict_rig_fit
    return model_from_fit(fit, rig)


def _replay(take, model, **options):
    from facepipe.pipeline.replay import NumpyEvaluator

    head, R, t, report = prepare_take(take, model, PrepareOptions(**options))
    out = NumpyEvaluator(model).evaluate(head)
    return np.einsum("tij,tvj->tvi", R, out) + t[:, None, :], report


@pytest.mark.ict
def test_ict_noisy_take_meets_the_acceptance_figures(ict_model):
    from facepipe.mocap import read_take
    from tests.conftest import ICT

    model = ict_model
    noisy = read_take(ICT / "noisy_mocap.csv", model.marker_names, units="cm")
    truth = np.load(ICT / "noisy_truth.npz")["positions"].astype(np.float64)
    clean = take_of(truth[:, model.handle_vertices], model.marker_names)

    def rms(out):
        return np.sqrt(((out - truth)[:, :9409] ** 2).sum(-1).mean(-1))

    e_noisy, report = _replay(noisy, model)
    e_clean = rms(_replay(clean, model)[0])
    e_noisy = rms(e_noisy)
    assert e_noisy.mean() <= 1.25 * e_clean.mean(), (e_noisy.mean(), e_clean.mean())
    # every frame, the take's first and last included: the pose and the residuals are smoothed over
    # the take without a window, so its ends are not left to their own frame's noise
    ratio = e_noisy / e_clean
    assert ratio.max() <= 1.5, np.round(ratio, 2)
    assert ratio[[0, -1]].max() <= 1.5
    assert report["total"]["missing"] == int(np.isnan(noisy.positions[..., 0]).sum())
    assert report["cleaning"]["noise"]["sigma"] == pytest.approx(0.02, rel=0.15)


@pytest.mark.ict
def test_ict_take_replays_the_same_from_every_format(ict_model, tmp_path):
    from facepipe.mocap import read_take, write_take
    from tests.conftest import ICT

    model = ict_model
    names = model.marker_names
    take = read_take(ICT / "noisy_mocap.csv", names, units="cm", frames="0:12")
    reference, _ = _replay(take, model)
    for fmt, suffix in [("c3d", ".c3d"), ("trc", ".trc"), ("vicon-csv", ".csv"), ("motive-csv", ".csv")]:
        path = tmp_path / f"take_{fmt}{suffix}"
        write_take(path, take, fmt, units="mm", subject="Actor")
        back = read_take(path, names, units="cm")
        assert back.source_units == "mm" and back.markers["subject"] == "Actor"
        out, _ = _replay(back, model)
        assert np.abs(out - reference).max() <= 1e-4, fmt


@pytest.mark.ict
def test_ict_replay_command_line(ict_model, tmp_path, capsys):
    from facepipe.cli.commands import main
    from facepipe.mocap import read_take, write_take
    from facepipe.io.model_file import save_model
    from tests.conftest import ICT

    model_path = tmp_path / "model.npz"
    save_model(model_path, ict_model.arrays, ict_model.meta)
    names = ict_model.marker_names
    take = read_take(ICT / "noisy_mocap.csv", names, units="cm", frames="0:10")
    c3d = tmp_path / "take.c3d"
    write_take(c3d, take, units="mm", subject="Actor")

    def run(*args):
        with pytest.raises(SystemExit) as exit_:
            main([str(a) for a in args])
        return exit_.value.code

    assert run("replay", c3d, "-m", model_path, "-o", tmp_path / "out", "--neutral-frame", 0, "--smooth", 1) == 0
    out = capsys.readouterr().out
    assert re.search(r"alignment: frame 0, scale 1\.00\d\d", out) and "mm -> cm" in out and "missing samples" in out
    info = json.loads((tmp_path / "out" / "replay.json").read_text())
    assert info["mocap"]["alignment"]["reference"] == "frame 0" and info["mocap"]["subject"] == "Actor"
    assert set(info["markers"]) == set(names) and info["mocap"]["cleaning"]["smooth_frames"] == 1.0
    # a facepipe CSV in mm (it cannot say so): the unit mismatch is caught, exit 2
    csv = tmp_path / "mm.csv"
    write_take(csv, take, "facepipe-csv", units="mm")
    assert run("replay", csv, "-m", model_path, "-o", tmp_path / "bad", "-q") == 2
    err = capsys.readouterr().err
    assert "seems to be in mm, not in cm" in err and "--take-units mm" in err
    assert run("replay", csv, "-m", model_path, "-o", tmp_path / "ok", "-q", "--take-units", "mm") == 0
    # three markers are missing in all 10 frames: the prior fills them, interpolation alone cannot
    assert run("replay", csv, "-m", model_path, "-o", tmp_path / "bad", "-q", "--take-units", "mm", "--no-clean") == 2
    assert "never visible in the take: M007, M018, S02" in capsys.readouterr().err
    assert run("replay", c3d, "-m", model_path, "-o", tmp_path / "bad", "-q", "--neutral-frame", 99) == 2
    assert "neutral frame 99 is not in the take" in capsys.readouterr().err
    assert run("replay", c3d, "-m", model_path, "-o", tmp_path / "bad", "-q", "--smooth", -1) == 2


# --------------------------------------------------------------------------- long takes, window by window


def long_take(rest, basis, n=900, noise=0.01, seed=2):
    """A noisy take of ``n`` frames with gaps, one of them across a window boundary."""
    rng = np.random.default_rng(seed)
    s = np.linspace(0, 6, n)
    weights = np.clip(np.stack([np.sin(np.pi * (s * (k + 1) / 3 + rng.uniform())) for k in range(K)], 1), 0, None)
    head = rest + np.einsum("tk,khc->thc", weights, basis)
    R = Rotation.from_rotvec(np.radians(10) * np.stack([np.sin(s), 0.5 * np.sin(0.7 * s + 1), 0.2 * s], 1)).as_matrix()
    t = np.stack([np.sin(0.5 * s), 0.3 * np.sin(s), -0.2 * s], 1) + [0.0, 150.0, 10.0]
    world = np.einsum("tij,thj->thi", R, head) + t[:, None, :] + rng.normal(scale=noise, size=(n, H, 3))
    world[190:215, 3] = np.nan  # across the boundary of 200-frame windows
    world[500:506, 7] = np.nan
    world[640, 11] = [40.0, 0.0, 0.0]  # an outlier
    return world, head


def test_long_takes_are_cleaned_window_by_window_as_well_as_whole():
    from facepipe.mocap.prepare import clean_margin, prepare_take_windows

    model, rest, basis, _, names = make_rig()
    world, head = long_take(rest, basis)
    take = take_of(world, names)
    assert len(world) > 200 + 2 * clean_margin(CleanOptions(), 30.0)
    whole, Rw, tw, rep_whole = prepare_take(take, model, window=10 ** 6)
    win, Rv, tv, rep_win = prepare_take(take, model, window=200)
    assert rep_win["cleaning"]["noise"]["windows"] == 5 and "windows" not in rep_whole["cleaning"]["noise"]

    def rms(x):
        return float(np.sqrt(np.mean(np.sum((x - head) ** 2, axis=-1))))

    assert rms(win) <= 1.1 * rms(whole)
    assert np.abs(win - whole).max() < 3 * 0.01  # the seams between windows: within the noise
    np.testing.assert_allclose(Rv, Rw, atol=2e-3)
    for key in ("frames", "missing", "gaps", "longest_gap", "interpolated", "from_prior", "outliers"):
        assert rep_win["total"][key] == rep_whole["total"][key], key
    assert rep_win["markers"][names[11]]["outliers"] == 1
    lo, hi = rep_win["cleaning"]["noise"]["sigma_range"]
    assert 0.5 * 0.01 < lo <= rep_win["cleaning"]["noise"]["sigma"] <= hi < 2 * 0.01
    json.dumps(rep_win)

    # a part replays exactly as in the whole take (the windows are fixed by the take's rows)
    part, Rp, tp, _ = prepare_take(take, model, PrepareOptions(frames=slice(350, 620)), window=200)
    np.testing.assert_array_equal(part, win[350:620])
    np.testing.assert_array_equal(Rp, Rv[350:620])

    # windows are cleaned as they are asked for; the report covers the selection at any time
    prepared = prepare_take_windows(take, model, PrepareOptions(frames=slice(150, 450)), window=200)
    assert prepared.n_windows == 3 and prepared.n_frames == 300
    windows = prepared.windows()
    first = next(windows)
    assert len(first[0]) == 50 and prepared.report()["total"]["frames"] == 600
    rest_ = list(windows)
    assert [len(w[0]) for w in rest_] == [200, 50] and prepared.report()["total"]["frames"] == 600
    np.testing.assert_array_equal(np.concatenate([first[0]] + [w[0] for w in rest_]), win[150:450])


@pytest.mark.parametrize("options", [{}, {"clean": False}, {"neutral_frame": 0}], ids=["clean", "no-clean", "neutral"])
@pytest.mark.parametrize("window", [200, 10 ** 6], ids=["windows", "whole"])
def test_a_prepared_takes_report_is_the_same_before_during_and_after_its_windows(options, window):
    """PreparedTake.report() is the whole selection's report whenever it is asked for: before any
    window is taken, between windows, after the last (and the windows are the same either way)."""
    from facepipe.mocap.prepare import prepare_take_windows

    model, rest, basis, _, names = make_rig()
    world, _ = long_take(rest, basis)
    take = take_of(world, names)
    take.markers = {"absent": []}
    selection = PrepareOptions(frames=slice(150, 650), **options)
    after = prepare_take_windows(take, model, selection, window=window)
    parts = list(after.windows())
    report_after = json.dumps(after.report())

    early = prepare_take_windows(take, model, selection, window=window)
    report_before = json.dumps(early.report())
    windows = early.windows()
    first = next(windows)
    report_between = json.dumps(early.report())
    parts_early = [first] + list(windows)
    assert report_before == report_between == report_after == json.dumps(early.report())
    assert after.n_windows == (1 if window > 1000 or options.get("clean") is False else 4)
    for a, b in zip(parts, parts_early, strict=True):
        for x, y in zip(a, b):
            np.testing.assert_array_equal(x, y)



@pytest.mark.filterwarnings("error")
def test_preparing_a_take_raises_no_warning_and_leaves_the_warning_filters_alone(monkeypatch):
    """A marker never seen, frames without markers, a neutral take that misses a marker: no warning
    from numpy, and no change to the process's warning filters on the way (they are process-wide:
    replay cleans on a second thread while the first may be warning)."""
    import warnings

    model, rest, basis, _, names = make_rig()
    world, _ = long_take(rest, basis)
    world[300:310] = np.nan  # frames without any marker
    still = np.repeat(rest[None], 5, 0)
    still[1:, 5] = np.nan  # a marker the neutral take shows once
    absent = world.copy()
    absent[:, 3] = np.nan  # a marker never seen (filled through the prior)
    take_absent = take_of(absent, names)
    take_absent.markers = {"absent": [names[3]]}

    def changes_filters(*args, **kwargs):
        raise AssertionError("a library call changed the warning filters")

    for take, options in ((take_absent, PrepareOptions()), (take_absent, PrepareOptions(stabilise=False)),
                          (take_of(world, names), PrepareOptions(neutral_take=take_of(still, names))),
                          (take_of(world, names), PrepareOptions(clean=False))):
        with monkeypatch.context() as patch:  # (pytest itself sets filters around the test)
            for name in ("catch_warnings", "simplefilter", "filterwarnings", "resetwarnings"):
                patch.setattr(warnings, name, changes_filters)
            head, *_ = prepare_take(take, model, options, window=200)
        assert np.isfinite(head).all()

def test_a_long_stretch_without_markers_is_cleaned_whole():
    model, rest, basis, _, names = make_rig()
    world, head = long_take(rest, basis)
    world[220:700] = np.nan  # no window from 200 to 600 can fit a pose
    out, *_, rep = prepare_take(take_of(world, names), model, window=200)
    assert np.isfinite(out).all() and "windows" not in rep["cleaning"]["noise"]
    assert any("cleaned whole" in n for n in rep["notes"])


# --------------------------------------------------------------------------- the take's ends


def test_whittaker_smoother_keeps_straight_motion_to_the_ends_and_matches_a_dense_solve():
    """The smoother against the dense normal equations; a straight line is kept exactly (no one-sided
    window's bias at the ends); GCV smooths white noise on a line hard and leaves a noise-free curve."""
    from facepipe.core.temporal import smooth_series, whittaker

    rng = np.random.default_rng(3)
    y = rng.normal(size=(40, 2))
    D = np.diff(np.eye(40), 2, axis=0)
    np.testing.assert_allclose(whittaker(y, 7.0), np.linalg.solve(np.eye(40) + 7.0 * D.T @ D, y), atol=1e-10)
    line = np.linspace(-1, 2, 40)[:, None] * [1.0, -3.0]
    np.testing.assert_allclose(whittaker(line, 1e5), line, atol=1e-9)
    z, lam, share, _ = smooth_series(line + 0.05 * rng.normal(size=line.shape))
    assert (lam >= 30).all() and (share < 0.3).all()
    assert np.abs(z - line).max() < 0.06  # the ends included (the noise is 0.05)
    curve = np.sin(np.linspace(0, 6, 40))[:, None]
    z, lam, _, _ = smooth_series(curve)
    assert np.abs(z - curve).max() < 1e-3


def test_the_first_and_last_frames_are_cleaned_as_well_as_the_rest():
    """Synthetic rig, noisy take with head motion: the pose and handles of the first and last frames
    are about as accurate as the middle's, and the temporal smoothing helps every part of the take."""
    _, rest, basis, stable, names = make_rig()
    world, head, R, t, _ = make_truth(rest, basis)
    errors = {}
    for temporal in (False, True):
        e = []
        for seed in range(4):
            noisy = world + np.random.default_rng(10 + seed).normal(scale=0.02, size=world.shape)
            res = clean_take(noisy, rest, basis, stable, np.arange(T) / 30.0, CleanOptions(temporal=temporal),
                             spacing=2.0)
            placed = np.einsum("tij,thj->thi", res.R, res.head) + res.t[:, None, :]
            e.append(np.sqrt(np.mean(np.sum((placed - world) ** 2, axis=-1), axis=1)))
        errors[temporal] = np.mean(e, axis=0)
    ends = np.r_[0:3, T - 3:T]
    middle = errors[True][10:T - 10].mean()
    # a smoother has neighbours on one side only at the ends: more noise stays there than in the
    # middle (for any smoother of a curved motion: a Gaussian-process posterior's end variance is
    # several times its middle's), but about what an unsmoothed frame has at most
    assert errors[True][ends].max() < 2.5 * middle, (errors[True][ends], middle)
    assert errors[True][ends].max() < 1.2 * errors[False][10:T - 10].mean()
    assert errors[True].mean() < 0.8 * errors[False].mean()
    assert errors[True][ends].mean() < errors[False][ends].mean()


def test_a_head_accelerating_at_the_takes_ends_is_placed_there_better_than_by_its_own_frame(monkeypatch):
    """Synthetic rig, a head turning back and forth (its largest acceleration at the first and last
    frames), noise of 0.02: over many draws the end frames' pose error (the true head placed by
    the cleaned pose, against the truth) is below what each end frame's own fit gives and below
    the smoother of second differences alone (which continues the ends as straight lines), and
    within 3× the interior's — the ends have neighbours on one side only, so never as good."""
    import facepipe.mocap.cleaning as cleaning

    _, rest, basis, stable, _ = make_rig()
    s = np.linspace(0, 1, T)
    weights = np.clip(np.stack([np.sin(np.pi * (s * (k + 1) + 0.3 * k)) for k in range(K)], 1), 0, None)
    head = rest + np.einsum("tk,khc->thc", weights, basis)
    rotvec = np.radians(15.0) * np.stack([np.cos(2 * np.pi * s), 0.5 * np.cos(2 * np.pi * s + 0.5),
                                          0.3 * np.sin(np.pi * s)], 1)
    R = Rotation.from_rotvec(rotvec).as_matrix()
    t = np.stack([np.cos(2 * np.pi * s), 0.5 * np.sin(3 * s), -s], 1) + [0.0, 150.0, 10.0]
    world = np.einsum("tij,thj->thi", R, head) + t[:, None, :]

    def pose_errors(temporal):
        e = []
        for seed in range(8):
            noisy = world + np.random.default_rng(50 + seed).normal(scale=0.02, size=world.shape)
            res = clean_take(noisy, rest, basis, stable, np.arange(T) / 30.0, CleanOptions(temporal=temporal),
                             spacing=2.0)
            placed = np.einsum("tij,thj->thi", res.R, head) + res.t[:, None, :]
            e.append(np.sqrt(np.mean(np.sum((placed - world) ** 2, axis=-1), axis=1)))
        return np.sqrt(np.mean(np.square(e), axis=0))  # (T,) RMS over the draws

    new, own = pose_errors(True), pose_errors(False)
    monkeypatch.setattr(cleaning, "ORDERS", (2,))
    straight = pose_errors(True)
    ends = [0, T - 1]
    assert new[ends].mean() < own[ends].mean(), (new[ends], own[ends])
    assert new[ends].mean() < straight[ends].mean(), (new[ends], straight[ends])
    assert new[ends].max() < 3.0 * np.median(new[10:T - 10]), (new[ends], np.median(new[10:T - 10]))
    assert np.median(new[10:T - 10]) < np.median(straight[10:T - 10])


def test_smoothing_with_known_noise_keeps_a_clean_jump_and_picks_the_least_risk():
    """C_p with the noise's variance: a noise-free step is left exactly (GCV's smallest λ rounds it
    off); on a noisy curve the chosen λ has the least unbiased risk among the candidates, checked
    with dense hat matrices."""
    from facepipe.core.temporal import LAMBDAS, smooth_series

    step = np.r_[np.zeros(20), np.ones(20)][:, None]
    z, lam, _, _ = smooth_series(step, noise_var=1e-12)
    np.testing.assert_array_equal(z, step)
    assert lam[0] == 0.0
    assert np.abs(smooth_series(step)[0] - step).max() > 1e-3  # what GCV alone does to it
    T = 50
    rng = np.random.default_rng(5)
    truth = np.sin(np.linspace(0, 4, T))[:, None]
    y = truth + rng.normal(scale=0.1, size=(T, 1))
    z, lam, _, _ = smooth_series(y, noise_var=0.01)
    D = np.diff(np.eye(T), 2, axis=0)

    def risk(l):
        Hm = np.linalg.inv(np.eye(T) + l * D.T @ D)
        return np.mean((y - Hm @ y) ** 2) - 0.01 + 2 * 0.01 * np.trace(Hm) / T

    assert risk(lam[0]) <= min(risk(l) for l in LAMBDAS) + 1e-12
    assert np.sqrt(np.mean((z - truth) ** 2)) < 0.6 * np.sqrt(np.mean((y - truth) ** 2))


def test_weight_variance_is_the_spread_of_least_squares_weights():
    """The expression weights' noise variance (diag of (Dᵀ W D)⁻¹) against the spread of weighted
    least-squares weights fitted to many noisy draws (markers with variance 1 / W)."""
    from facepipe.mocap.cleaning import _weight_variance

    rng = np.random.default_rng(3)
    basis = rng.normal(size=(4, 12, 3))
    basis[1] = basis[0] + 0.3 * basis[1]  # two examples that move the markers alike
    W = rng.uniform(0.5, 2.0, size=(1, 12))
    A = basis.reshape(4, -1).T
    w = np.repeat(W[0], 3)
    draws = rng.normal(size=(20000, 36)) / np.sqrt(w)
    fits = np.linalg.solve(A.T @ (w[:, None] * A), (A.T * w) @ draws.T).T
    np.testing.assert_allclose(_weight_variance(W, basis), fits.var(axis=0), rtol=0.05)


def test_pose_variance_is_the_spread_of_weighted_rigid_fits():
    """The rotation's and the centroid translation's noise variance per component against the spread
    of weighted rigid fits to many noisy draws of the same points (variance 1 / W per coordinate)."""
    from facepipe.core.rigid import rigid_fit
    from facepipe.mocap.cleaning import _pose_variance

    rng = np.random.default_rng(4)
    points = rng.normal(scale=[3.0, 2.0, 1.0], size=(15, 3))
    W = rng.uniform(0.5, 2.0, size=15)
    n = 20000
    noisy = points + rng.normal(size=(n, 15, 3)) / np.sqrt(W)[None, :, None]
    R, t = rigid_fit(points, noisy, np.broadcast_to(W, (n, 15)))
    rotation = Rotation.from_matrix(R).as_rotvec()
    centroid = W @ points / W.sum()
    moved = np.einsum("nij,j->ni", R, centroid) + t
    rot_var, trans_var = _pose_variance(W[None], points[None])
    assert rotation.var(axis=0).mean() == pytest.approx(rot_var, rel=0.05)
    assert moved.var(axis=0).mean() == pytest.approx(trans_var, rel=0.05)


def test_noise_sigma_is_the_capture_noise_not_what_the_fit_leaves():
    """The per-frame fit absorbs a share (parameters / equations) of the noise; the reported σ is
    the markers' own (the residual alone reads about 6 % low on this rig: 11 of 90 per frame)."""
    _, rest, basis, stable, names = make_rig()
    world, _, _, _, _ = make_truth(rest, basis)
    sigmas = []
    for seed in range(4):
        noisy = world + np.random.default_rng(20 + seed).normal(scale=0.02, size=world.shape)
        sigmas.append(clean_take(noisy, rest, basis, stable, np.arange(T) / 30.0, spacing=2.0).report["noise"]["sigma"])
    assert np.mean(sigmas) == pytest.approx(0.02, rel=0.03)


@pytest.mark.parametrize("T, lam", [(3, 1.0), (4, 0.5), (37, 3.0), (60, 1e7), (50, 0.01)])
def test_noise_variance_share_is_the_variance_of_smoothed_white_noise(T, lam):
    from facepipe.core.temporal import noise_variance_share, whittaker

    D = np.diff(np.eye(T), 2, axis=0)
    H = np.linalg.inv(np.eye(T) + lam * D.T @ D)
    share = noise_variance_share(T, lam, block=7)  # several blocks, one of them partial
    np.testing.assert_allclose(share, np.diag(H @ H.T), rtol=1e-8, atol=1e-12)
    assert np.all(share <= np.diag(H) + 1e-12)  # H's eigenvalues lie in [0, 1]
    if T >= 4:  # second check: the spread of many smoothed white-noise series
        noise = np.random.default_rng(T).normal(size=(T, 20000))
        np.testing.assert_allclose(whittaker(noise, lam).var(axis=1), share, rtol=0.05)
        assert share[0] > share[T // 2]  # an end keeps more noise than the middle


def test_active_set_step_resolves_only_the_frames_whose_set_changed():
    """The active-set step of a batch equals each frame's own (a weight at zero that its step would
    make negative leaves the set, the system is solved again), leaves the caller's set untouched,
    and solves again only the frames whose set changed."""
    from facepipe.mocap import pose_expression

    rng = np.random.default_rng(5)
    n, n_pose, K = 12, 6, 20
    P = n_pose + K
    M = rng.normal(size=(n, P + 10, P))
    A = np.einsum("nip,niq->npq", M, M)
    g = rng.normal(size=(n, P))
    C = np.where(rng.random((n, K)) < 0.6, 0.0, rng.random((n, K)))  # many weights at zero ...
    C[n // 2:] += 0.1  # ... in half the frames: the others settle at once
    free = rng.random((n, K)) < 0.9
    free_before = free.copy()
    solved = []
    original = pose_expression._solve_active
    cleaning_solve = lambda A_, g_, f_, p_: solved.append(len(A_)) or original(A_, g_, f_, p_)  # noqa: E731
    try:
        pose_expression._solve_active = cleaning_solve
        step, out = pose_expression._solve_active_set(A, g, C, free, n_pose, K)
    finally:
        pose_expression._solve_active = original
    assert np.array_equal(free, free_before)
    passes = 0
    for i in range(n):  # each frame alone, by the rule
        f = free[i:i + 1].copy()
        for k in range(K + 1):
            s = original(A[i:i + 1], g[i:i + 1], f, n_pose)
            leave = f & (C[i:i + 1] <= 0) & (s[:, n_pose:] < 0)
            if not leave.any():
                break
            f &= ~leave
        passes = max(passes, k)
        np.testing.assert_allclose(step[i], s[0], rtol=0, atol=1e-9 * np.abs(s).max())
        assert np.array_equal(out[i], f[0])
    assert passes >= 2 and solved[0] == n and len(solved) > 2 and all(m <= n // 2 for m in solved[1:])
