"""Validation of the local-strain model's kernel width and ridge (pipeline.strain_validation)."""

import re

import numpy as np
import pytest

from facepipe.core.strain_details import fit_strain_details
from facepipe.pipeline.strain_validation import choose_strain, held_out_errors, strain_grid, strain_table
from facepipe.pipeline.tune import choose_parameters
from facepipe.sample_rig import write_sample_rig


@pytest.fixture(scope="module")
def strain_config(tmp_path_factory):
    """The sample rig (wrinkles nonlinear in the motion) with method local_strain, learning from the
    first 30 frames of its take, and a small candidate grid."""
    d = tmp_path_factory.mktemp("strain_validation")
    write_sample_rig(d, n_vertices=3000, n_examples=6, n_frames=40)
    cfg = d / "sample.toml"
    text = cfg.read_text().replace('method = "wpsd"', 'method = "local_strain"', 1)
    text = text.replace('sequence = ""', 'sequence = "take_truth.npz"\nsequence_frames = [0, 30]', 1)
    cfg.write_text(text + "\n[tune]\nk_stretch = [0.0, 1.0]\nstrain_width = [0.04, 0.16]\n"
                   "strain_ridge = [0.1, 1.0]\nfolds = 3\nsample_vertices = 400\n")
    return cfg


def test_held_out_errors_match_refitting_each_split():
    rng = np.random.default_rng(3)
    n_poses, n_vertices = 12, 37
    strains = rng.normal(scale=0.05, size=(n_poses, n_vertices, 3))
    strains[0] = 0.0
    details = np.tanh(-20 * strains[..., :1]) * rng.normal(size=(1, n_vertices, 3))
    details[0] = 0.0
    splits = [(np.r_[0, 1:8], np.r_[8:12]), (np.r_[0, 5:12], np.r_[1:5])]
    grid = strain_grid([0.03, 0.1], [0.01, 1.0], 0.05, 0.3)
    assert (0.05, 0.3) in grid and len(grid) == 9
    errors = held_out_errors(strains, details, splits, grid, chunk=8)
    for w, r in grid:
        expected = np.full(n_poses - 1, np.nan)
        for train, held in splits:  # a second implementation: a plain solve per split
            model = fit_strain_details(strains[train], details[train], w, r)
            res = model.evaluate(strains[held]) - details[held]
            expected[held - 1] = np.sqrt((res ** 2).sum(-1).mean(-1))
        # poses 5–7 are held out by neither split: NaN in both (assert_allclose takes NaN as equal)
        np.testing.assert_allclose(errors[(w, r)], expected, rtol=1e-8, atol=1e-12)


def test_choice_takes_the_best_on_time_blocks_that_harms_no_held_out_expression():
    large = np.array([1.0, 1.0, 2.0, 2.0])  # two meshes, then two frames
    errors = {(0.1, 1.0): np.array([1.0, 1.0, 1.5, 1.5]),   # the config's values
              (0.02, 1.0): np.array([1.3, 1.0, 0.5, 0.5]),  # best on frames, harms an expression
              (0.05, 1.0): np.array([1.0, 1.005, 1.0, 1.0])}
    rows, default_row = strain_table(errors, large, np.array([2, 3]), np.array([0, 1]), (0.1, 1.0), 1.01,
                                     {"k_stretch": 0.0})
    assert default_row["cv_rms"] == 1.5
    chosen = choose_strain(rows)
    assert (chosen["strain_width"], chosen["no_harm"]) == (0.05, True)
    # without time blocks: the held-out expressions' mean, no worse than the config's values
    rows, _ = strain_table(errors, large, np.zeros(0, int), np.array([0, 1]), (0.1, 1.0), 1.01, {})
    assert choose_strain(rows)["strain_width"] == 0.1  # (0.05 ties within the limit but is not better)


def test_fit_validates_a_local_strain_rig(strain_config):
    from facepipe.pipeline.rig import load_rig

    rig = load_rig(strain_config)
    report = choose_parameters(rig)
    assert report["validated"] and report["method"] == "local_strain"
    chosen = report["chosen"]
    assert (rig.config.psd.strain_width, rig.config.psd.strain_ridge) == (chosen["strain_width"],
                                                                          chosen["strain_ridge"])
    pairs = {(r["strain_width"], r["strain_ridge"]) for r in report["details"]}
    assert len(pairs) == len(report["details"]) >= 4
    best = min(r["cv_rms"] for r in report["details"] if r["accepted"])
    assert chosen["cv_rms"] == best


@pytest.mark.parametrize("line", ["strain_width = [0.0, 0.1]", "strain_ridge = []", "strain_ridge = [-1.0]"])
def test_bad_strain_candidates_are_refused_naming_the_key(strain_config, line):
    from facepipe.errors import InputError
    from facepipe.io.config import load_config

    bad = strain_config.parent / "bad.toml"  # (beside the rig's files)
    key = line.split()[0]
    bad.write_text(re.sub(rf"^{key} = .*$", line, strain_config.read_text(), count=1, flags=re.M))
    with pytest.raises(InputError, match=key):
        load_config(bad)
