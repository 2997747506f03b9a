"""fit --tune: validation-driven shell stiffness, WPSD falloff, regularisation and basis size."""

import json
from pathlib import Path

import numpy as np
import pytest

from facepipe.errors import InputError
from facepipe.io.config import TuneConfig, load_config
from facepipe.pipeline.rig import load_rig
from facepipe.sample_rig import write_sample_rig
from facepipe.core.shell import marker_spacing, shell_basis
from facepipe.pipeline.tune import tune_rig, tuned_config
from tests.conftest import run_cli

SMALL = dict(k_stretch=[0.0, 0.3, 3.0, 30.0], beta_scale=[0.5, 1.0], smoothing=[0.0, 0.1], max_poses=4, folds=3)


@pytest.fixture(scope="module")
def sample(tmp_path_factory):
    out = tmp_path_factory.mktemp("tune_rig")
    return write_sample_rig(out, n_vertices=2500, n_examples=6, n_frames=12)


@pytest.fixture(scope="module")
def lookup_report(sample):
    rig = load_rig(sample["config"])
    return rig, tune_rig(rig, TuneConfig(**SMALL))


def test_defaults_are_candidates_and_never_beaten(lookup_report):
    rig, report = lookup_report
    d, c = report["default"], report["chosen"]
    assert d["k_stretch"] in report["candidates"]["k_stretch"]
    assert c["cv_rms"] <= d["cv_rms"]
    # every candidate of the grid was scored at every basis size
    combos = {(r["k_stretch"], r["beta_scale"], r["smoothing"]) for r in report["details"]}
    assert (c["k_stretch"], c["beta_scale"], c["smoothing"]) in combos
    assert c["accepted"]
    # the choice validates as well as the best accepted candidate (within the noise of the folds)
    best = min(r["cv_rms"] for r in report["details"] if r["accepted"])
    assert c["cv_rms"] <= 1.05 * best
    tied_larger = [r for r in report["details"] if r["accepted"] and r["poses"] > c["poses"]
                   and r["cv_rms"] <= best]
    assert not tied_larger  # nothing as good with a larger basis was passed over
    assert report["seconds"]["total"] > 0 and len(report["folds"]) >= 2


def test_sample_rig_lands_in_a_good_region(lookup_report):
    """The chosen stiffness is the best of the shell sweep and the details help on held-out poses."""
    rig, report = lookup_report
    shell = {r["k_stretch"]: r["large_rms"] for r in report["shell"]}
    assert shell[report["chosen"]["k_stretch"]] == min(shell.values())
    assert report["chosen"]["cv_rms"] < report["chosen"]["large_cv_rms"]
    assert not report["harm"]


def test_recovers_the_stiffness_examples_were_made_with(sample):
    """Examples that are exact shell deformations at k_stretch = 3 have zero large-scale error there."""
    rig = load_rig(sample["config"])
    rest, handles = rig.mesh.vertices, rig.handles
    B = shell_basis(rest, rig.mesh.faces, handles, rig.anchors, k_stretch=3.0, k_bend=1.0,
                    spacing=marker_spacing(rest, handles))
    rng = np.random.default_rng(1)
    u = rng.normal(scale=0.05 * marker_spacing(rest, handles), size=(5, len(handles), 3))
    rig.example_positions = rest + np.einsum("vh,ehc->evc", B, u)
    rig.example_names = [f"pose{i}" for i in range(5)]
    report = tune_rig(rig, TuneConfig(k_stretch=[0.0, 0.3, 3.0, 30.0], beta_scale=[1.0], smoothing=[0.0],
                                      max_poses=2, folds=2))
    assert report["chosen"]["k_stretch"] == 3.0
    assert min(r["large_rms"] for r in report["shell"]) < 1e-6 * marker_spacing(rest, handles)


def test_details_that_do_harm_fall_back(sample):
    """Details uncorrelated with the strain cannot be predicted on held-out poses: fall back.

    The examples are one expression at several strengths (so a held-out one is a seen kind of
    strain and the novelty gate lets the details through) plus noise off the markers.
    """
    rig = load_rig(sample["config"])
    rng = np.random.default_rng(2)
    rest = rig.mesh.vertices
    scale = 0.1 * marker_spacing(rest, rig.handles)
    strengths = np.linspace(0.4, 1.0, 6)
    noise = rng.normal(scale=scale, size=(6,) + rest.shape)
    noise[:, rig.handles] = 0.0
    rig.example_positions = rest + strengths[:, None, None] * (rig.example_positions[0] - rest) + noise
    rig.example_names = [f"pose{i}" for i in range(6)]
    report = tune_rig(rig, TuneConfig(k_stretch=[0.0], beta_scale=[1.0], smoothing=[0.0], max_poses=3, folds=3))
    assert report["harm"] and report["fallback"]
    assert tuned_config(rig.config, report).psd.method == "none"
    report = tune_rig(rig, TuneConfig(k_stretch=[0.0], beta_scale=[1.0], smoothing=[0.0], max_poses=3, folds=3,
                                      fallback=False))
    assert report["harm"] and not report["fallback"]


def test_cli_tune_writes_report_and_bake_carries_the_choice(sample, tmp_path):
    cfg = Path(sample["config"]).parent / "tuned.toml"  # beside the sample config: its paths are relative
    cfg.write_text(Path(sample["config"]).read_text(encoding="utf-8")
                   + "\n[tune]\nk_stretch = [0.0, 1.0, 10.0]\nbeta_scale = [1.0]\nsmoothing = [0.0, 0.1]\n"
                   "max_poses = 3\nfolds = 3\n", encoding="utf-8")
    fit = tmp_path / "fit.npz"
    assert run_cli("fit", cfg, "-o", fit, "--tune", "-q") == 0
    report = json.loads((tmp_path / "fit.tune.json").read_text())
    assert (tmp_path / "fit.tune.png").stat().st_size > 0
    chosen = report["chosen"]
    fit_report = json.loads((tmp_path / "fit.json").read_text())
    assert fit_report["tune"]["chosen"] == chosen
    assert fit_report["k_stretch"] == chosen["k_stretch"]
    model = tmp_path / "model.npz"
    assert run_cli("bake", fit, "-o", model, "-q") == 0
    from facepipe.io.model_file import load_model

    meta = load_model(model).meta
    assert meta["tuned"]["k_stretch"] == chosen["k_stretch"] and meta["shell"]["k_stretch"] == chosen["k_stretch"]
    assert len(meta["basis"]) - 1 == (0 if report["fallback"] else chosen["poses"])


@pytest.mark.parametrize("table, message", [
    ("k_stretch = 3.0", "k_stretch"),
    ("smoothing = [-1.0]", "smoothing"),
    ("folds = 1", "folds"),
    ("fallback = 'no'", "fallback"),
    ("colour = 1", "unknown key"),
])
def test_bad_tune_table(sample, tmp_path, table, message):
    cfg = tmp_path / "bad.toml"
    cfg.write_text(Path(sample["config"]).read_text(encoding="utf-8") + f"\n[tune]\n{table}\n", encoding="utf-8")
    with pytest.raises(InputError, match=message):
        load_config(cfg)


def test_tune_refuses_what_it_cannot_validate(sample):
    rig = load_rig(sample["config"])
    rig.config.shell.method = "rbf"
    with pytest.raises(InputError, match="stiffness"):
        tune_rig(rig, TuneConfig(**SMALL))
    rig = load_rig(sample["config"])
    rig.example_positions, rig.example_names = rig.example_positions[:2], rig.example_names[:2]
    with pytest.raises(InputError, match="at least 3 example meshes"):
        tune_rig(rig, TuneConfig(**SMALL))


def test_cli_tune_bad_input_exits_2(sample, tmp_path):
    cfg = Path(sample["config"]).parent / "bad_tune.toml"
    cfg.write_text(Path(sample["config"]).read_text(encoding="utf-8") + "\n[tune]\nfolds = 1\n", encoding="utf-8")
    out = tmp_path / "fit.npz"
    assert run_cli("fit", cfg, "-o", out, "--tune", "-q") == 2
    assert not out.exists() and not (tmp_path / "fit.tune.json").exists()


# ----------------------------------------------------------------------------- validated by default


def test_expression_splits_hold_every_example_out_once():
    from facepipe.pipeline.tune import expression_splits

    names = ["smile_L", "smile_R", "blink_L", "blink_R", "jawOpen", "pucker", "frown"]
    splits = expression_splits(names, 3)
    held = np.sort(np.concatenate([h for _, h in splits]))
    assert np.array_equal(held, np.arange(1, len(names) + 1))  # pose indices: every example once
    for train, h in splits:
        assert train[0] == 0 and not set(train) & set(h)  # the rest pose always trains, never held
        assert set(train) | set(h) == set(range(len(names) + 1))
        sides = {names[j - 1].rsplit("_", 1)[0] for j in h}
        assert not any(names[j - 1].rsplit("_", 1)[0] in sides for j in train[1:])  # halves go together


def test_stopping_clearly_worse_candidates_early_keeps_the_choice(tmp_path, monkeypatch):
    """The candidates dropped after the first folds are never the ones the full search picks."""
    import facepipe.pipeline.tune as tune_module

    config = write_sample_rig(tmp_path, n_vertices=2000, n_examples=12, n_frames=4)["config"]
    table = dict(k_stretch=[0.0, 3.0], beta_scale=[0.1, 1.0, 8.0], smoothing=[0.0, 1.0], max_poses=4, folds=6)
    pruned = tune_rig(load_rig(config), TuneConfig(**table))
    monkeypatch.setattr(tune_module, "CLEARLY_WORSE_SE", np.inf)
    full = tune_rig(load_rig(config), TuneConfig(**table))
    assert pruned["stopped_early"] and not full["stopped_early"]
    assert pruned["chosen"] == full["chosen"]
    assert pruned["default"] == full["default"]
    dropped = {(r["k_stretch"], r["beta_scale"], r["smoothing"]) for r in pruned["stopped_early"]}
    kept = {(r["k_stretch"], r["beta_scale"], r["smoothing"]) for r in pruned["details"]}
    assert not dropped & kept
    chosen = full["chosen"]
    assert (chosen["k_stretch"], chosen["beta_scale"], chosen["smoothing"]) not in dropped


def test_clearly_worse_needs_a_clear_paired_difference():
    from facepipe.pipeline.tune import _clearly_worse

    rng = np.random.default_rng(0)
    base = rng.uniform(1.0, 2.0, size=(3, 8))
    errors = {("a", 1, 0, 0.1): base, ("b", 1, 0, 0.1): base * 1.2,  # worse on every example
              ("c", 1, 0, 0.1): base + rng.normal(scale=0.05, size=base.shape),  # as good, within noise
              ("d", 1, 0, 0.1): base * 1.5}  # the defaults' reference: kept whatever its error
    live = [k[:3] for k in errors]
    worse = _clearly_worse(errors, live, np.arange(8), keep=("d", 1, 0))
    assert worse == [("b", 1, 0)]
    assert _clearly_worse(errors, live, np.arange(2), keep=("d", 1, 0)) == []  # too few examples to tell


def test_fit_validates_by_default_and_no_tune_keeps_the_config(sample, tmp_path):
    cfg = Path(sample["config"]).parent / "small_tune.toml"
    cfg.write_text(Path(sample["config"]).read_text(encoding="utf-8")
                   + "\n[tune]\nk_stretch = [0.0, 1.0]\nbeta_scale = [1.0]\nsmoothing = [0.0]\n"
                   "max_poses = 3\nfolds = 3\n", encoding="utf-8")
    assert run_cli("fit", cfg, "-o", tmp_path / "default.npz", "-q") == 0
    assert run_cli("fit", cfg, "-o", tmp_path / "alias.npz", "--tune", "-q") == 0
    assert run_cli("fit", cfg, "-o", tmp_path / "fixed.npz", "--no-tune", "-q") == 0
    default = json.loads((tmp_path / "default.json").read_text())
    alias = json.loads((tmp_path / "alias.json").read_text())
    fixed = json.loads((tmp_path / "fixed.json").read_text())
    assert default["validation"] == {"validated": True} and (tmp_path / "default.tune.json").is_file()
    assert default["tune"]["chosen"] == alias["tune"]["chosen"] and default["basis"] == alias["basis"]
    assert fixed["validation"] == {"validated": False, "reason": "disabled"} and "tune" not in fixed
    assert not (tmp_path / "fixed.tune.json").exists()
    config = load_config(cfg)
    assert fixed["k_stretch"] == config.shell.k_stretch and len(fixed["basis"]) - 1 == config.psd.max_poses
    # bake CONFIG validates the same way
    assert run_cli("bake", cfg, "-o", tmp_path / "model.npz", "-q") == 0
    from facepipe.io.model_file import load_model

    assert load_model(tmp_path / "model.npz").meta["tuned"]["k_stretch"] == default["tune"]["chosen"]["k_stretch"]


def test_fit_warns_and_keeps_the_defaults_when_the_examples_cannot_validate(sample, tmp_path, capsys):
    cfg = Path(sample["config"]).parent / "two_examples.toml"
    text = Path(sample["config"]).read_text(encoding="utf-8")
    rig = load_rig(sample["config"])
    assert len(rig.example_names) >= 2
    pattern = next(line for line in text.splitlines() if line.startswith("meshes"))
    first_two = [str(p) for p in sorted(Path(sample["config"]).parent.glob("expressions/*.obj"))[:2]]
    cfg.write_text(text.replace(pattern, "meshes = " + json.dumps(first_two)), encoding="utf-8")
    assert run_cli("fit", cfg, "-o", tmp_path / "fit.npz") == 0
    out = capsys.readouterr().out
    assert "warning: parameters not validated" in out and "at least 3 example meshes" in out
    report = json.loads((tmp_path / "fit.json").read_text())
    assert report["validation"]["validated"] is False and "tune" not in report


def test_time_blocks_are_contiguous_cover_every_frame_once_and_keep_neighbours_out():
    from facepipe.pipeline.tune import time_block_splits

    n_meshes, n_frames = 4, 40
    splits = time_block_splits(n_meshes, n_frames, 5)
    held = np.concatenate([h for _, h in splits])
    assert sorted(held.tolist()) == list(range(n_meshes + 1, n_meshes + 1 + n_frames))
    for train, h in splits:
        assert np.all(np.diff(h) == 1)  # one contiguous block
        assert set(range(n_meshes + 1)) <= set(train.tolist())  # the rest pose and every mesh train
        frames = train[train > n_meshes]
        # no training frame within the margin (a quarter block, 2 frames) of the block
        gap = np.min(np.abs(frames[:, None] - h[None, :]))
        assert gap > 2 and not set(frames.tolist()) & set(h.tolist())


def test_performance_choice_prefers_new_mixtures_under_the_no_harm_rule():
    from facepipe.pipeline.tune import choose_for_performance, performance_table

    frames, meshes = np.arange(3, 7), np.arange(3)
    large = {0.0: np.array([1.0, 1.0, 1.0, 2.0, 2.0, 2.0, 2.0])}

    def errors(expr, frame):
        e = np.full((3, 7), np.nan)
        e[1:, :3], e[1:, 3:] = expr, frame
        return e

    table = {(0.0, 1.0, 0.0, 0.1): errors(1.0, 1.5),  # no harm, helps on mixtures
             (0.0, 1.0, 0.0, 0.3): errors(1.2, 1.0),  # best on mixtures, harms a new expression
             (0.0, 2.0, 0.0, 0.1): errors(0.9, 1.8)}  # best on expressions
    rows, default = performance_table(table, large, frames, meshes, (0.0, 1.0, 0.0, 0.1), 2, 2, 1.01)
    chosen = choose_for_performance(rows)
    assert (chosen["novelty_tau"], chosen["beta_scale"], chosen["poses"]) == (0.1, 1.0, 2)
    assert chosen["no_harm"] and chosen["cv_rms"] == 1.5 and chosen["large_cv_rms"] == 2.0
    # every candidate harms: the least harmful, flagged, never the details switched off
    harmful = {key: errors(1.5, e) for key, e in zip(table, (1.5, 1.0, 1.2))}
    harmful[(0.0, 2.0, 0.0, 0.1)] = errors(1.1, 1.9)
    rows, _ = performance_table(harmful, large, frames, meshes, (0.0, 1.0, 0.0, 0.1), 2, 2, 1.01)
    chosen = choose_for_performance(rows)
    assert not chosen["no_harm"] and chosen["beta_scale"] == 2.0


def test_a_training_performance_is_validated_on_held_out_time_blocks(tmp_path, capsys):
    """With [examples] sequence, fit validates on held-out blocks of its frames and on held-out
    expressions, reports both, and prints and saves what it chose and why."""
    rig_dir = tmp_path / "rig"
    paths = write_sample_rig(rig_dir, n_vertices=2500, n_examples=6, n_frames=40)
    cfg = Path(paths["config"])
    text = cfg.read_text().replace('sequence = ""', 'sequence = "take_truth.npz"\nsequence_frames = [0, 30]')
    text = text.replace('fit = "interpolate"', 'fit = "least-squares"')
    cfg.write_text(text + "\n[tune]\nk_stretch = [0.0, 3.0]\nbeta_scale = [1.0]\nnovelty_tau = [0.15]\n"
                   "max_poses = 8\nfolds = 3\n")
    out = tmp_path / "fit.npz"
    assert run_cli("fit", str(cfg), "-o", str(out)) == 0
    text_out = capsys.readouterr().out
    report = json.loads(out.with_suffix(".tune.json").read_text())
    assert report["validation"] == "time blocks + expressions" and len(report["time_blocks"]) == 3
    assert report["time_blocks"][0] == ["take_truth:0", "take_truth:9"]
    c = report["chosen"]
    assert {"cv_rms", "large_cv_rms", "expression_cv_rms", "worst_expression_vs_large"} <= set(c)
    assert "held-out time blocks" in text_out and "new expressions" in text_out
