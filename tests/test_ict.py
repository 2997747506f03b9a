"""Regression on the ICT FaceKit (real face, 26 expression scans, 120-frame take with truth).

The issue's acceptance figures: fit on the 26 expressions, replay train_mocap's markers, error
over the face area [0, 9409): WPSD at P = 12 ≤ 0.70× and PSD ≤ 0.80× the large-scale-only error.
"""

import numpy as np
import pytest

from facepipe.pipeline.evaluate import frame_errors
from facepipe.io.model_file import model_from_fit
from facepipe.pipeline.replay import NumpyEvaluator
from tests.conftest import ict_or_skip

pytestmark = pytest.mark.ict
FACE = slice(0, 9409)


@pytest.fixture(scope="module")
def ict_fit(ict_rig_fit):
    rig, fit = ict_rig_fit
    truth = np.load(ict_or_skip() / "train_truth.npz")["positions"].astype(np.float64)
    return rig, fit, truth


def _replay_error(rig, fit, truth, method, n_poses):
    ev = NumpyEvaluator(model_from_fit(fit, rig, method, n_poses))
    out = ev.evaluate(truth[:, rig.handles])
    rms, _ = frame_errors(out, truth, FACE)
    return rms


def test_ict_feature_graph_and_fit_report(ict_fit):
    rig, fit, _ = ict_fit
    r = fit.report
    assert r["handles"] == 96 and r["vertices"] == 11248
    # a planar graph over 96 markers: between a spanning tree and a triangulation
    assert 95 <= r["feature_edges"] <= 3 * 96 - 6
    assert len(r["curves"]["wpsd"]) == 13 and len(r["curves"]["psd"]) == 13


def test_ict_details_beat_large_scale(ict_fit):
    rig, fit, truth = ict_fit
    large = _replay_error(rig, fit, truth, "none", 0).mean()
    wpsd = _replay_error(rig, fit, truth, "wpsd", 12).mean()
    psd = _replay_error(rig, fit, truth, "psd", 12).mean()
    assert wpsd <= 0.70 * large, (wpsd, large)
    assert psd <= 0.80 * large, (psd, large)
