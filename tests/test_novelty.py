import logging

import numpy as np
import pytest
from scipy.optimize import nnls

from facepipe.pipeline.baselines import global_blend_weights, local_blend_operator, local_blend_positions
from facepipe.core.psd import edge_weight_matrix, fit_details
from facepipe.core.novelty import CONFIDENCE_TOLERANCE, edge_distances, novelty_batched_steps, novelty_gate


def _graph(F=30, seed=0):
    rng = np.random.default_rng(seed)
    pos = rng.uniform(0, 10, size=(F, 2))
    D = np.linalg.norm(pos[:, None] - pos[None], axis=-1)
    return D


def _alpha(V, F, K=4, seed=1):
    rng = np.random.default_rng(seed)
    idx = np.stack([rng.choice(F, K, replace=False) for _ in range(V)])
    w = rng.uniform(0.2, 1, size=(V, K))
    w /= w.sum(1, keepdims=True)
    return idx, w, edge_weight_matrix(idx, w, F)


def test_gate_trusts_the_span_of_the_examples_and_fades_outside():
    F, E = 30, 4
    rng = np.random.default_rng(2)
    ex = rng.normal(scale=0.1, size=(E, F))
    _, _, alpha = _alpha(50, F)
    gate = novelty_gate(ex, _graph(F), alpha, tau=0.2, radius=3.0, max_edges=8)
    mixes = rng.uniform(0, 1, size=(6, E)) @ ex
    assert np.allclose(gate.novelty(mixes), 0.0, atol=1e-6)
    assert np.allclose(gate.confidence(mixes), 1.0, atol=1e-5)
    # strain orthogonal to every example at every site: fully novel
    Q, _ = np.linalg.qr(np.concatenate([ex.T, rng.normal(size=(F, F - E))], axis=1))
    novel = Q[:, E:].T[:3]
    rho = gate.novelty(novel)
    assert ((rho >= 0) & (rho <= 1)).all() and rho.mean() > 0.3
    c = gate.confidence(novel)
    assert ((c > 0) & (c < 1)).all()
    # at rest (no strain) the gate is open
    assert np.allclose(gate.confidence(np.zeros((1, F))), 1.0)


def test_gate_disabled_with_tau_zero_and_keeps_interpolation():
    F, E, V = 20, 5, 40
    rng = np.random.default_rng(3)
    feats = np.concatenate([np.zeros((1, F)), rng.normal(scale=0.1, size=(E, F))])
    details = np.concatenate([np.zeros((1, V, 3)), rng.normal(size=(E, V, 3))])
    idx, w, alpha = _alpha(V, F)
    model = fit_details("wpsd", feats, details, list(range(E + 1)), "interpolate", alpha)
    model.gate = novelty_gate(feats[1:], _graph(F), alpha, tau=0.2, radius=3.0)
    # the examples are in their own span: the gate leaves their interpolation exact
    assert np.abs(model.evaluate(feats) - details).max() < 1e-5
    off = novelty_gate(feats[1:], _graph(F), alpha, tau=0.0, radius=3.0)
    assert np.allclose(off.confidence(rng.normal(size=(2, F))), 1.0)


def test_edge_distances_symmetric_zero_diagonal_for_points():
    D = _graph(6)
    edges = np.array([[0, 1], [2, 3], [4, 5]])
    ed = edge_distances(D, edges)
    assert np.allclose(ed, ed.T)
    assert np.allclose(np.diag(ed), 0.5 * np.array([D[0, 1], D[2, 3], D[4, 5]]))


def test_global_blend_weights_recover_convex_mixture():
    rng = np.random.default_rng(4)
    prior = rng.normal(size=(5, 12, 3))
    w = np.array([0.1, 0.2, 0.0, 0.3, 0.4])
    got = global_blend_weights(prior, np.einsum("e,ehc->hc", w, prior)[None])
    assert np.allclose(got[0], w, atol=1e-4)


def test_local_blend_shapes_reproduce_an_example():
    F, E, V = 25, 4, 30
    rng = np.random.default_rng(5)
    ex = rng.normal(scale=0.1, size=(E, F))
    idx, w, _ = _alpha(V, F, K=8)
    M = local_blend_operator(ex, idx, w, ridge=1e-9)
    rest = rng.normal(size=(V, 3))
    offsets = rng.normal(size=(E, V, 3))
    pos = local_blend_positions(M, idx, ex[2:3], rest, offsets)
    assert np.allclose(pos[0], rest + offsets[2], atol=1e-4)


def _overlapping_gate():
    """A gate over overlapping examples and one that barely strains the sites, with queries inside
    the cone, outside it and in the span but not the cone."""
    F, E = 24, 7
    rng = np.random.default_rng(5)
    base = rng.normal(scale=0.1, size=(3, F))
    ex = np.concatenate([base, base[:2] + 0.3 * base[2], 0.02 * rng.normal(size=(2, F))])  # overlapping, weak
    _, _, alpha = _alpha(20, F)
    gate = novelty_gate(ex, _graph(F), alpha, tau=0.2, radius=3.0, max_edges=10)
    queries = np.concatenate([rng.uniform(0, 1, size=(4, E)) @ ex, rng.normal(scale=0.1, size=(4, F)),
                              rng.uniform(-1, 1, size=(4, E)) @ ex])
    return gate, queries


def test_novelty_is_the_non_negative_least_squares_residual():
    """ρ equals the residual of an exact NNLS (scipy) at every site, also where examples overlap
    and where one example barely strains the site (where clipped least squares is far off):
    by default (a few batched steps, the rest handed to the exact solver) and by the batched steps
    alone, run to convergence."""
    gate, queries = _overlapping_gate()
    steps = novelty_batched_steps(gate.examples.shape[1])
    fit = gate.novelty_fit(queries)
    assert fit.unconverged == 0 and fit.iterations <= steps and fit.finished_exactly > 0
    batched = gate.novelty_fit(queries, max_iterations=20000, finish_exactly=False)
    assert batched.unconverged == 0 and steps < batched.iterations < 20000
    x = queries[:, gate.index] * gate.sqrt_weight
    for q in range(len(queries)):
        for s in range(x.shape[1]):
            b = x[q, s].astype(np.float64)
            _, r = nnls(gate.examples[s].T.astype(np.float64), b)
            for f in (fit, batched):
                assert abs(f.rho[q, s] - r ** 2 / (b @ b + 1e-12)) < 1e-5
    assert np.array_equal(gate.novelty(queries), fit.rho)


def test_fits_stopped_by_the_cap_are_finished_exactly(monkeypatch):
    """The batched fits the cap stops are finished by an exact NNLS: ρ as if they had converged."""
    gate, queries = _overlapping_gate()
    capped = gate.novelty_fit(queries, tolerance=1e-14, max_iterations=3, finish_exactly=False)
    assert capped.iterations == 3 and 0 < capped.unconverged <= capped.rho.size
    finished = gate.novelty_fit(queries, tolerance=1e-14, max_iterations=3)
    assert finished.unconverged == 0 and finished.finished_exactly == capped.unconverged
    x = queries[:, gate.index] * gate.sqrt_weight
    for q in range(len(queries)):
        for s in range(x.shape[1]):
            b = x[q, s].astype(np.float64)
            _, r = nnls(gate.examples[s].T.astype(np.float64), b)
            assert abs(finished.rho[q, s] - r ** 2 / (b @ b + 1e-12)) < 1e-9


def test_novelty_fits_left_unconverged_are_counted_and_logged(caplog, monkeypatch):
    import scipy.optimize

    gate, queries = _overlapping_gate()
    capped = gate.novelty_fit(queries, tolerance=1e-14, max_iterations=3, finish_exactly=False)

    def exact_solver_gives_up(*args, **kwargs):
        raise RuntimeError("Maximum number of iterations reached.")

    monkeypatch.setattr(scipy.optimize, "nnls", exact_solver_gives_up)  # (imported where it is called)
    with caplog.at_level(logging.WARNING, logger="facepipe.core.novelty"):
        rho = gate.novelty(queries, tolerance=1e-14, max_iterations=3)
    assert np.array_equal(rho, capped.rho)
    assert gate.unconverged_fits == capped.unconverged
    assert f"{capped.unconverged} of {capped.rho.size} site fits stopped after 3 iterations" in caplog.text
    # converged fits add nothing and say nothing
    monkeypatch.undo()
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="facepipe.core.novelty"):
        gate.novelty(queries)
    assert gate.unconverged_fits == capped.unconverged and not caplog.text


def test_novelty_fit_stops_each_fit_on_its_own():
    """Where a fit stops does not depend on the other queries in the batch (up to round-off)."""
    gate, queries = _overlapping_gate()
    together = gate.novelty_fit(queries).rho
    alone = np.concatenate([gate.novelty_fit(queries[q:q + 1]).rho for q in range(len(queries))])
    assert np.allclose(alone, together, rtol=0, atol=1e-12)


def test_confidence_settles_fits_within_its_tolerance():
    """A replay's confidences stop each fit once its coefficients leave so little unexplained that
    the confidence is within CONFIDENCE_TOLERANCE of 1: the same confidences as fits run to
    convergence (and as exact NNLS) to that tolerance, in fewer steps where the queries are
    mixtures of the examples, and the fits of the other queries unchanged."""
    gate, queries = _overlapping_gate()
    settled = gate.settled_fraction()
    assert gate.site_confidence(np.array([settled]))[0] == pytest.approx(1.0 - CONFIDENCE_TOLERANCE, rel=1e-9)
    full = gate.novelty_fit(queries)
    early = gate.novelty_fit(queries, settled=settled)
    stopped_early = early.rho != full.rho
    assert stopped_early.any() and (early.rho[stopped_early] <= settled).all()
    assert np.abs(gate.site_confidences(queries) - gate.site_confidence(full.rho)).max() <= CONFIDENCE_TOLERANCE
    x = queries[:, gate.index] * gate.sqrt_weight
    exact = np.array([[nnls(gate.examples[s].T.astype(np.float64), x[q, s])[1] ** 2 / (x[q, s] @ x[q, s] + 1e-12)
                       for s in range(x.shape[1])] for q in range(len(queries))])
    assert np.abs(gate.site_confidences(queries) - gate.site_confidence(exact)).max() <= 2 * CONFIDENCE_TOLERANCE
    mixtures = queries[:4]
    assert gate.novelty_fit(mixtures, settled=settled).iterations < gate.novelty_fit(mixtures).iterations
    # the per-vertex confidence is the per-site one through α
    np.testing.assert_allclose(gate.confidence(queries), (gate.alpha @ gate.site_confidences(queries).T).T)


def test_novelty_fits_of_many_queries_match_one_at_a_time():
    """Fits run in units of a few queries of one site: a batch of more queries than a unit holds
    (the last unit padded) gives each query the ρ it gets alone."""
    gate, queries = _overlapping_gate()
    many = np.concatenate([queries, queries[::-1], queries[:5]])  # 29 queries: 3 full units and a padded one
    together = gate.novelty_fit(many).rho
    alone = np.concatenate([gate.novelty_fit(many[q:q + 1]).rho for q in range(len(many))])
    assert np.allclose(alone, together, rtol=0, atol=1e-12)
    assert np.allclose(together[:12], together[12:24][::-1], rtol=0, atol=1e-12)


# ----------------------------------------------------------------------------- the gate's motion part


def _surface_graph(seed=4):
    """A small planar marker graph in the xy plane: handles, feature edges, distances."""
    from scipy.spatial import Delaunay

    rng = np.random.default_rng(seed)
    xy = rng.uniform(0, 10, size=(40, 2))
    rest = np.concatenate([xy, np.zeros((40, 1))], axis=1)
    tri = Delaunay(xy).simplices
    edges = np.unique(np.sort(np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [0, 2]]]), axis=1), axis=0)
    marker_distance = np.linalg.norm(rest[:, None] - rest[None], axis=-1)
    return rest, edges, marker_distance


def _strain(handles, rest, edges):
    from facepipe.core.strain import edge_lengths, strain_features

    return strain_features(handles, edges, edge_lengths(rest, edges))


def test_motion_part_separates_a_bulge_from_a_scaled_example():
    """Out-of-surface motion changes the feature edges' lengths only to second order: an
    expression that sinks the markers where an example slides them in the plane can show that
    example's scaled strain. The strain test passes it; the motion part does not, while genuine
    non-negative mixtures of the examples stay seen."""
    rest, edges, marker_distance = _surface_graph()
    rng = np.random.default_rng(5)
    H, F = len(rest), len(edges)
    # examples: smooth in-plane motions (stretches and shears of regions) of the marker sheet
    centres = rng.uniform(2, 8, size=(4, 2))
    moves = np.zeros((4, H, 3))
    for e, c in enumerate(centres):
        fall = np.exp(-np.sum((rest[:, :2] - c) ** 2, axis=1) / 6.0)
        moves[e, :, :2] = 0.4 * fall[:, None] * (rest[:, :2] - c) * (1 if e % 2 else -1)
    feats = _strain(rest + moves, rest, edges)
    site_distance = edge_distances(marker_distance, edges)
    alpha = edge_weight_matrix(np.arange(F)[:, None], np.ones((F, 1)), F)
    kwargs = dict(example_displacements=moves, marker_distance=marker_distance, edges=edges)
    gate = novelty_gate(feats, site_distance, alpha, tau=0.2, radius=3.0, max_edges=24, **kwargs)
    strain_only = novelty_gate(feats, site_distance, alpha, tau=0.2, radius=3.0, max_edges=24)
    assert gate.has_motion and not strain_only.has_motion
    # mixtures: small weights keep the strain close to linear in the motion
    w = rng.uniform(0, 0.1, size=(5, 4))
    mix = np.einsum("qe,ehc->qhc", w, moves)
    rho_mix = gate.novelty(_strain(rest + mix, rest, edges), mix)
    assert rho_mix.max() < 0.05
    # a scaled example plus a sinking of its region along the normal (z): the strain barely moves
    scaled = 0.1 * moves[0]
    bulge = scaled.copy()
    bulge[:, 2] = -0.5 * np.exp(-np.sum((rest[:, :2] - centres[0]) ** 2, axis=1) / 6.0)
    f_bulge = _strain(rest + bulge, rest, edges)[None]
    near = np.argsort(np.linalg.norm(0.5 * (rest[edges[:, 0], :2] + rest[edges[:, 1], :2]) - centres[0], axis=1))[:5]
    assert strain_only.novelty(f_bulge)[0, near].max() < 0.2  # the strain test calls it seen ...
    assert gate.novelty(f_bulge, bulge[None])[0, near].min() > 0.5  # ... the motion says otherwise
    # a translation of the whole sheet is no motion relative to the sites
    shifted = mix + np.array([0.3, -0.2, 0.5])
    assert np.allclose(gate.novelty(_strain(rest + shifted, rest, edges), shifted), rho_mix, atol=1e-6)


def test_motion_part_matches_exact_nnls_of_each_part():
    """ρ with the motion part: the larger of the strain's and the motion's unexplained fractions,
    each from its own non-negative fit (checked against SciPy's NNLS per site)."""
    rest, edges, marker_distance = _surface_graph(seed=6)
    rng = np.random.default_rng(7)
    H, F = len(rest), len(edges)
    moves = rng.normal(scale=0.1, size=(5, H, 3))
    feats = _strain(rest + moves, rest, edges)
    alpha = edge_weight_matrix(np.arange(F)[:, None], np.ones((F, 1)), F)
    gate = novelty_gate(feats, edge_distances(marker_distance, edges), alpha, tau=0.2, radius=3.0, max_edges=16,
                        example_displacements=moves, marker_distance=marker_distance, edges=edges)
    queries = rng.normal(scale=0.1, size=(3, H, 3)) + 0.5 * moves[:3]
    qf = _strain(rest + queries, rest, edges)
    rho = gate.novelty(qf, queries, tolerance=1e-12, max_iterations=20000)
    strain = qf[:, gate.index] * gate.sqrt_weight
    motion = gate.motion_vectors(queries)
    for q in range(3):
        for s in range(0, F, 7):
            parts = []
            for x, A in ((strain[q, s], gate.examples[s]), (motion[q, s], gate.motion_examples[s])):
                c, _ = nnls(A.T.astype(np.float64), x)
                r = x - A.T.astype(np.float64) @ c
                parts.append(r @ r / (x @ x + 1e-12))
            assert abs(rho[q, s] - min(1.0, max(parts))) < 1e-3
    with pytest.raises(ValueError, match="displacements"):
        gate.novelty(qf)


def test_batched_steps_before_the_exact_solver_grow_as_the_examples_get_fewer():
    """Few examples make a batched step cheap against one exact solve: more steps before it."""
    assert novelty_batched_steps(8) == 64 and novelty_batched_steps(26) == 19
    assert novelty_batched_steps(106) == novelty_batched_steps(1000) == 16
    assert novelty_batched_steps(0) >= 16
