from pathlib import Path

import numpy as np
import pytest

from facepipe.errors import InputError
from facepipe.core.strain import auto_feature_graph, edge_lengths, graph_from_pairs, strain_features
from tests.conftest import grid


def _rotation(seed):
    q, _ = np.linalg.qr(np.random.default_rng(seed).normal(size=(3, 3)))
    return q * np.sign(np.linalg.det(q))


def test_strain_invariant_under_rigid_motion():
    rng = np.random.default_rng(0)
    P = rng.normal(size=(20, 3))
    edges = np.array([[i, j] for i in range(20) for j in range(i + 1, 20)][:40])
    rest = edge_lengths(P, edges)
    Q = P + 0.05 * rng.normal(size=P.shape)
    f = strain_features(Q, edges, rest)
    moved = Q @ _rotation(3).T + np.array([4.0, -2.0, 7.0])
    assert np.allclose(strain_features(moved, edges, rest), f, atol=1e-12)
    assert np.allclose(strain_features(P, edges, rest), 0)


def test_strain_analytic_uniform_scaling():
    P = np.random.default_rng(1).normal(size=(6, 3))
    edges = np.array([[0, 1], [2, 5], [3, 4]])
    f = strain_features(1.1 * P, edges, edge_lengths(P, edges))
    assert np.allclose(f, 0.1)


def test_auto_graph_is_planar_like_and_connected():
    V, F = grid(30, 30)
    markers = np.array([i * 30 + j for i in range(2, 30, 6) for j in range(2, 30, 6)])
    edges = auto_feature_graph(V, F, markers)
    M = len(markers)
    # a planar triangulation has at most 3M - 6 edges; a grid of markers has at least its 4-neighbour edges
    assert 2 * M - 2 * int(np.sqrt(M)) <= len(edges) <= 3 * M - 6
    import scipy.sparse as sp
    from scipy.sparse.csgraph import connected_components

    g = sp.coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(M, M))
    assert connected_components(g, directed=False)[0] == 1
    # no edge spans more than about two marker spacings
    L = edge_lengths(V[markers], edges)
    assert L.max() < 2.5 * np.median(L)


def test_auto_graph_does_not_cross_a_hole():
    V, F = grid(40, 20, curved=False)
    # cut a slit: drop triangles across the middle row between columns 5 and 35
    cy = V[F].mean(axis=1)
    slit = (np.abs(cy[:, 1]) < 0.3) & (np.abs(cy[:, 0]) < 3.5)
    F = F[~slit]
    top = [np.argmin(np.linalg.norm(V - [x, 1.0, 0], axis=1)) for x in (-2.0, 0.0, 2.0)]
    bottom = [np.argmin(np.linalg.norm(V - [x, -1.0, 0], axis=1)) for x in (-2.0, 0.0, 2.0)]
    markers = np.array(top + bottom)
    edges = auto_feature_graph(V, F, markers)
    across = [(a, b) for a, b in edges if (a < 3) != (b < 3)]
    # only the outermost markers can meet around the slit's ends, never the middle ones
    assert all(1 not in (a, b) and 4 not in (a, b) for a, b in across)


def test_graph_from_pairs_validates_names():
    names = ["A", "B", "C"]
    assert graph_from_pairs([("B", "A"), ("A", "B"), ("C", "B")], names).tolist() == [[0, 1], [1, 2]]
    with pytest.raises(InputError, match="line 2: marker 'X'"):
        graph_from_pairs([("A", "B"), ("X", "B")], names)
    with pytest.raises(InputError, match="itself"):
        graph_from_pairs([("A", "A")], names)


def test_geodesics_shared_with_a_second_process_match_scipy():
    from scipy.sparse.csgraph import dijkstra

    from facepipe.pipeline.geodesics import Geodesics, geodesic_from
    from facepipe.core.strain import edge_graph

    V, F = grid(150, 140)
    g = edge_graph(V, F)
    sources = np.arange(0, len(V), len(V) // 100)[:100]  # 21000 vertices x 100 sources: two processes
    reference = dijkstra(g, directed=False, indices=sources)
    assert np.array_equal(geodesic_from(g, sources), reference)
    assert np.array_equal(geodesic_from(g, sources[:3]), reference[:3])
    # the child starts on the first sources while this process waits; it takes the rest from the end
    job = Geodesics(g, sources, background=True, device=False)
    import time

    time.sleep(1.5)
    assert np.array_equal(job.finish(), reference)
    assert job.child_sources > 0


def _cpu_device_or_skip():
    from facepipe.opencl.geodesics import _cpu_device

    if _cpu_device() is None:
        pytest.skip("no OpenCL CPU device with double precision here")


def test_geodesics_on_the_device_equal_scipy_to_the_bit():
    """The bucket Dijkstra on the OpenCL CPU device: the same distances as SciPy's heap, bit for bit,
    on uneven edge lengths (a jittered grid, a sliver-heavy strip) and with unreachable vertices."""
    from scipy.sparse.csgraph import dijkstra

    from facepipe.pipeline.geodesics import Geodesics
    from facepipe.core.strain import edge_graph

    _cpu_device_or_skip()
    rng = np.random.default_rng(3)
    V, F = grid(90, 70)
    V = V + rng.uniform(-0.3, 0.3, V.shape) * [1.0 / 89, 1.0 / 69, 0.0]
    V[:, 2] = 0.05 * np.sin(7 * V[:, 0]) * np.cos(5 * V[:, 1])
    island = np.array([[5.0, 5.0, 0.0], [6.0, 5.0, 0.0], [5.0, 6.0, 0.0]])  # a separate triangle
    V = np.vstack([V, island])
    F = np.vstack([F, len(V) - 3 + np.array([[0, 1, 2]])])
    g = edge_graph(V, F)
    sources = np.r_[np.arange(0, len(V) - 3, 97), [len(V) - 1]]
    job = Geodesics(g, sources, background=True, device=True)
    assert job.where == "opencl"
    got = job.finish()
    assert np.array_equal(got, dijkstra(g, directed=True, indices=sources))
    assert np.isinf(got[0, -1]) and np.isinf(got[-1, 0])
    job.close()


def test_device_geodesics_decline_what_buckets_cannot_do(monkeypatch):
    """Edge lengths too uneven for a ring of buckets, limited searches, or a device that fails at run
    time: SciPy computes the same rows."""
    from scipy.sparse.csgraph import dijkstra

    from facepipe.opencl import geodesics as device_geodesics
    from facepipe.pipeline.geodesics import Geodesics
    from facepipe.core.strain import edge_graph

    assert device_geodesics.ring_size(np.array([1.0, 2.0, 3.0])) == (8, 1.0 * (1 - 1e-9))  # 3 / δ + 2 → 8
    assert device_geodesics.ring_size(np.array([1e-6, 1.0])) is None
    assert device_geodesics.ring_size(np.array([0.0, 1.0])) is None
    V, F = grid(30, 20)
    g = edge_graph(V, F)
    sources = np.arange(0, len(V), 40)
    reference = dijkstra(g, directed=True, indices=sources)
    limited = Geodesics(g, sources, limit=0.2, background=True, device=True)
    assert limited.where != "opencl"
    assert np.array_equal(limited.finish(), dijkstra(g, directed=True, indices=sources, limit=0.2))
    limited.close()

    _cpu_device_or_skip()

    def broken(self):
        raise RuntimeError("the driver lost the device")

    monkeypatch.setattr(device_geodesics.DeviceGeodesics, "finish", broken)
    job = Geodesics(g, sources, background=True, device=True)
    assert job.where == "opencl"
    assert np.array_equal(job.finish(), reference)
    assert job.where == "here after the device failed"
    job.close()


def test_geodesics_when_the_child_fails(monkeypatch):
    """A second process that cannot start (or dies) leaves its sources to this one: same distances."""
    from scipy.sparse.csgraph import dijkstra

    from facepipe.pipeline import background
    from facepipe.pipeline.geodesics import Geodesics
    from facepipe.core.strain import edge_graph

    V, F = grid(60, 50)
    g = edge_graph(V, F)
    sources = np.arange(0, len(V), 30)

    def no_process(*args, **kwargs):
        raise OSError("no processes here")

    monkeypatch.setattr(background.subprocess, "Popen", no_process)
    job = Geodesics(g, sources, background=True, device=False)
    assert np.array_equal(job.finish(), dijkstra(g, directed=False, indices=sources))
    assert job.child_sources == 0


def test_geodesics_without_room_for_the_shared_rows(monkeypatch):
    """No space for the file both processes map (a full temp disk): every source is computed here,
    and no temp folder is left behind."""
    import errno
    import tempfile

    from scipy.sparse.csgraph import dijkstra

    from facepipe.pipeline.geodesics import Geodesics
    from facepipe.core.strain import edge_graph

    V, F = grid(40, 30)
    g = edge_graph(V, F)
    sources = np.arange(0, len(V), 25)
    made = []
    real = tempfile.TemporaryDirectory

    def recording(*args, **kwargs):
        made.append(real(*args, **kwargs))
        return made[-1]

    def full(*args):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(tempfile, "TemporaryDirectory", recording)
    monkeypatch.setattr("os.posix_fallocate", full, raising=False)
    job = Geodesics(g, sources, background=True, device=False)
    assert made and not Path(made[0].name).exists()
    assert np.array_equal(job.finish(), dijkstra(g, directed=False, indices=sources))
    assert job.child_sources == 0


def test_edge_graph_from_the_meshs_edges_is_the_same_graph():
    """The geodesics' graph made from a mesh's cached unique edges is the one found from its faces:
    same edges, lengths and order, to the bit; each edge once each way, at its length."""
    from facepipe.core.mesh import Mesh
    from facepipe.core.strain import edge_graph

    V, F = grid(9, 7)
    mesh = Mesh(V, np.arange(0, 3 * len(F) + 1, 3), F.ravel())
    a, b = edge_graph(V, F), edge_graph(V, F, mesh.edges)
    assert np.array_equal(a.indptr, b.indptr) and np.array_equal(a.indices, b.indices)
    assert np.array_equal(a.data, b.data)
    i, j = mesh.edges.T
    assert a.nnz == 2 * len(mesh.edges)
    assert np.array_equal(np.asarray(a[i, j]).ravel(), np.linalg.norm(V[i] - V[j], axis=1))
