import os
import threading

import numpy as np
import pytest

from facepipe import parallel
from facepipe.core import psd, tangent_frames
from facepipe.core.psd import edge_weight_matrix, solve_rbf, wpsd_distances, wpsd_edge_weights
from facepipe.mocap import facepipe_csv
from facepipe.mocap.facepipe_csv import read_csv_take, write_take_csv
from tests.conftest import grid
from tests.test_mocap import NAMES, make_take


@pytest.fixture(autouse=True)
def _no_limits(monkeypatch):
    """Every test starts from the environment alone, and leaves no override behind."""
    monkeypatch.delenv("FACEPIPE_THREADS", raising=False)
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    parallel.set_thread_count(None)
    yield
    parallel.set_thread_count(None)


def _threads_seen(monkeypatch, module, name):
    """Wrap ``module.name`` so that the threads it runs on are recorded."""
    seen = set()
    original = getattr(module, name)

    def recording(*args, **kwargs):
        seen.add(threading.get_ident())
        return original(*args, **kwargs)

    monkeypatch.setattr(module, name, recording)
    return seen


def test_thread_count_follows_the_environment(monkeypatch):
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0, 1, 2, 3}, raising=False)
    assert parallel.thread_count() == 4
    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    assert parallel.thread_count() == 1
    monkeypatch.setenv("OMP_NUM_THREADS", "3,2")  # one count per nesting level: the outer one
    assert parallel.thread_count() == 3
    monkeypatch.setenv("FACEPIPE_THREADS", "2")  # facepipe's own setting wins
    assert parallel.thread_count() == 2
    monkeypatch.setenv("FACEPIPE_THREADS", "many")  # unusable: the next limit applies
    assert parallel.thread_count() == 3
    parallel.set_thread_count(5)  # a program's own choice (batch workers) wins over both
    assert parallel.thread_count() == 5
    parallel.set_thread_count(None)
    assert parallel.thread_count() == 3
    with pytest.raises(ValueError):
        parallel.set_thread_count(0)


def test_thread_count_follows_the_affinity(monkeypatch):
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {2, 5, 7}, raising=False)
    monkeypatch.setattr(os, "cpu_count", lambda: 64)
    assert parallel.available_cpus() == 3 and parallel.thread_count() == 3


def test_map_blocks_in_order_on_threads_and_here_with_one():
    calls = []

    def square(i):
        calls.append(threading.get_ident())
        return i * i

    parallel.set_thread_count(4)
    assert parallel.map_blocks(square, range(40)) == [i * i for i in range(40)]
    calls.clear()
    parallel.set_thread_count(1)
    assert parallel.map_blocks(square, range(40)) == [i * i for i in range(40)]
    assert set(calls) == {threading.get_ident()}


def test_map_blocks_raises_the_first_error_after_the_running_calls_end():
    parallel.set_thread_count(3)
    running = [0]
    lock = threading.Lock()

    def work(i):
        with lock:
            running[0] += 1
        try:
            if i in (3, 10):
                raise ValueError(str(i))
            threading.Event().wait(0.001)
        finally:
            with lock:
                running[0] -= 1

    with pytest.raises(ValueError, match="^3$"):
        parallel.map_blocks(work, range(30))
    assert running[0] == 0


def test_map_in_order_yields_in_order_with_a_bounded_number_under_way():
    """Results come in the order of the items; no more than ``ahead`` calls are under way or
    done but not yet taken (a movie of thousands of frames keeps a few in memory); one thread
    runs them here; an error comes at its turn, and closing the stream early leaves no call running."""
    parallel.set_thread_count(3)
    lock = threading.Lock()
    state = {"started": 0, "taken": 0, "most": 0, "running": 0}

    def work(i):
        with lock:
            state["started"] += 1
            state["running"] += 1
            state["most"] = max(state["most"], state["started"] - state["taken"])
        threading.Event().wait(0.002 * (i % 3))  # finishing out of order
        with lock:
            state["running"] -= 1
        return i * i

    out = []
    for value in parallel.map_in_order(work, range(50), ahead=4):
        out.append(value)
        with lock:
            state["taken"] += 1
    assert out == [i * i for i in range(50)]
    assert state["most"] <= 4 + 1  # the ones under way and the one being handed over
    # calls that each hold a third of the memory allowed: two under way at most, however many threads
    state.update(started=0, taken=0, most=0)
    for value in parallel.map_in_order(work, range(20), ahead=8, item_bytes=parallel.ORDERED_MEMORY // 3 + 1):
        with lock:
            state["taken"] += 1
    assert state["most"] <= 2 + 1
    # an error at its turn, the calls before it delivered
    def fails_at_7(i):
        if i == 7:
            raise ValueError("7")
        return i

    got = []
    with pytest.raises(ValueError, match="^7$"):
        for value in parallel.map_in_order(fails_at_7, range(30)):
            got.append(value)
    assert got == list(range(7))
    # a consumer that stops early: nothing left running
    stream = parallel.map_in_order(work, range(100), ahead=6)
    next(stream)
    stream.close()
    assert state["running"] == 0
    # one thread: here, in order
    parallel.set_thread_count(1)
    idents = []
    assert list(parallel.map_in_order(lambda i: idents.append(threading.get_ident()) or i, range(5))) == list(range(5))
    assert set(idents) == {threading.get_ident()}


def test_nested_blocks_run_in_their_worker():
    parallel.set_thread_count(2)

    def outer(i):
        return parallel.map_blocks(lambda j: (i, j, threading.get_ident()), range(3))

    for rows in parallel.map_blocks(outer, range(4)):
        assert len({ident for _, _, ident in rows}) == 1


def _wpsd_problem(V=600, E=6, F=12, vertices=slice(None)):
    """A WPSD fit's kernel matrices (V, E, E) and details (E, V, 3), as the fit lays them out; of
    ``vertices`` alone where given (the same problem without the others)."""
    rng = np.random.default_rng(0)
    features = rng.normal(scale=0.1, size=(E, F))
    features[0] = 0.0
    details = rng.normal(scale=0.05, size=(E, V, 3))
    details[0] = 0.0
    index = np.stack([rng.choice(F, 5, replace=False) for _ in range(V)]).astype(np.int32)
    weight = rng.uniform(0.1, 1.0, size=(V, 5))
    alpha = edge_weight_matrix(index, (weight / weight.sum(1, keepdims=True)).astype(np.float32), F)[vertices]
    phi = np.moveaxis(wpsd_distances(features, features, alpha), 1, 0)
    return phi, details[:, vertices]


@pytest.mark.parametrize("limit", ["FACEPIPE_THREADS", "OMP_NUM_THREADS"])
def test_one_thread_from_the_environment_runs_the_solve_here_with_the_same_result(monkeypatch, limit):
    phi, details = _wpsd_problem()
    many = solve_rbf(phi, details, chunk=50)
    monkeypatch.setenv(limit, "1")
    seen = _threads_seen(monkeypatch, psd, "_solve_block")
    one = solve_rbf(phi, details, chunk=50)
    assert seen == {threading.get_ident()}
    assert np.array_equal(one[0], many[0]) and np.array_equal(one[1], many[1])


def test_vertices_without_details_are_zero_and_the_others_solved_as_alone():
    """Vertices whose details are zero in every pose (skin the anchors hold) get the zero solution
    without a solve; every other vertex's weights are the same bit for bit as when the vertices
    without details are left out of the problem."""
    phi, details = _wpsd_problem()
    still = np.zeros(len(phi), dtype=bool)
    still[::3] = True
    details[:, still] = 0.0
    calls = []
    original = psd._solve_block

    def counted(block_phi, *args):
        calls.append(len(block_phi))
        return original(block_phi, *args)

    psd._solve_block = counted
    try:
        w, c = solve_rbf(phi, details, chunk=50)
    finally:
        psd._solve_block = original
    assert sum(calls) == (~still).sum()
    assert not w[still].any() and not c[still].any()
    moving = np.flatnonzero(~still)
    w_without, c_without = solve_rbf(*_wpsd_problem(vertices=moving), chunk=50)
    assert np.array_equal(w[moving], w_without) and np.array_equal(c[moving], c_without)


def test_one_allowed_cpu_runs_the_edge_weights_here(monkeypatch):
    rng = np.random.default_rng(1)
    dist = rng.uniform(0, 10, size=(8, 3000))
    edges = np.array([[i, j] for i in range(8) for j in range(i + 1, 8)])
    rest = rng.uniform(1, 3, size=len(edges))
    many = wpsd_edge_weights(dist, edges, rest, beta=1.0, chunk=256)
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0}, raising=False)
    seen = _threads_seen(monkeypatch, np, "argsort")
    one = wpsd_edge_weights(dist, edges, rest, beta=1.0, chunk=256)
    assert seen == {threading.get_ident()}
    assert np.array_equal(one[0], many[0]) and np.array_equal(one[1], many[1])


def test_frames_of_a_large_batch_follow_the_thread_count(monkeypatch):
    V, F = grid(100, 100)
    nb = tangent_frames.frame_neighbors(F, len(V))
    poses = V[None] + 0.01 * np.sin(np.arange(100))[:, None, None] * V[None, :, [1, 2, 0]]  # 100 × 10k vertices
    parallel.set_thread_count(3)
    many = tangent_frames.local_frames(poses, F, nb)
    monkeypatch.setenv("FACEPIPE_THREADS", "1")
    parallel.set_thread_count(None)
    seen = _threads_seen(monkeypatch, tangent_frames, "vertex_normals")
    one = tangent_frames.local_frames(poses, F, nb)
    assert seen == {threading.get_ident()}
    assert np.array_equal(one, many)


def test_take_parsing_follows_the_thread_count(tmp_path, monkeypatch):
    take = make_take(T=300, missing=0.1, seed=3)
    write_take_csv(tmp_path / "t.csv", take)
    monkeypatch.setattr(facepipe_csv, "_BLOCK_BYTES", 500)  # ~6 rows a block
    parallel.set_thread_count(4)
    many = read_csv_take(tmp_path / "t.csv", NAMES)
    parallel.set_thread_count(1)
    seen = _threads_seen(monkeypatch, facepipe_csv, "_parse_block_fast")
    one = read_csv_take(tmp_path / "t.csv", NAMES)
    assert seen == {threading.get_ident()}
    np.testing.assert_array_equal(one.positions, many.positions)


def test_serial_blas_limits_blas_to_one_thread_and_restores_it():
    import numpy as np  # noqa: F401 - loads the BLAS threadpoolctl reports on
    from threadpoolctl import threadpool_info

    from facepipe.parallel import serial_blas

    def blas_threads():
        return [i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"]

    before = blas_threads()
    with serial_blas():
        assert all(n == 1 for n in blas_threads())
    assert blas_threads() == before
