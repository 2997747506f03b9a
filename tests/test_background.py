"""BackgroundCall: a value computed in a second process equals the one computed here, and any
failure of the child falls back to computing here (raising this process's own error)."""

import numpy as np
import pytest

from facepipe.pipeline.background import BackgroundCall


def scaled(a, k):
    return a * k


def fails(a):
    raise ValueError(f"bad input of shape {a.shape}")


def test_value_from_the_child_process_equals_the_value_here():
    a = np.random.default_rng(0).normal(size=(1000, 3))
    job = BackgroundCall(scaled, a, 2.5)
    assert np.array_equal(job.result(), a * 2.5)
    assert job.where == "process" and job.seconds >= 0
    assert job.result() is job.result()  # collected once
    inline = BackgroundCall(scaled, a, 2.5, background=False)
    assert np.array_equal(inline.result(), a * 2.5) and inline.where == "here"


def test_a_failing_child_is_retried_here_and_raises_here():
    job = BackgroundCall(fails, np.zeros((2, 3)))
    with pytest.raises(ValueError, match=r"shape \(2, 3\)"):
        job.result()
    assert job.where == "here after the process failed"


def test_unpicklable_call_runs_here():
    job = BackgroundCall(lambda a: a + 1, np.ones(3))
    assert np.array_equal(job.result(), np.full(3, 2.0)) and job.where == "here"


def test_cancel_stops_the_child_and_removes_its_folder():
    import os

    job = BackgroundCall(scaled, np.ones(3), 2.0)
    folder = job._dir
    job.cancel()
    assert not os.path.exists(folder)
