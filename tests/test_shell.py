import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from facepipe.core.shell import (CholeskyFactor, constrained_split, constrained_system, cotmatrix, large_scale_positions, massmatrix, shell_basis, shell_operator)
from tests.conftest import grid


def test_cotmatrix_symmetric_psd_rows_sum_zero(sheet):
    V, F = sheet
    K = cotmatrix(V, F)
    assert abs(K - K.T).max() < 1e-12
    assert np.allclose(K.sum(axis=1), 0, atol=1e-10)
    assert np.linalg.eigvalsh(K.toarray()).min() > -1e-9


def test_cotmatrix_kills_linear_functions_inside_a_flat_sheet():
    V, F = grid(curved=False)
    K = cotmatrix(V, F)
    f = 2.0 * V[:, 0] - 3.0 * V[:, 1] + 1.0
    interior = (np.abs(V[:, 0]) < 4.9) & (np.abs(V[:, 1]) < 4.9)
    assert np.abs((K @ f)[interior]).max() < 1e-9


def test_cotmatrix_survives_degenerate_triangle():
    V = np.array([[0, 0, 0], [1, 0, 0], [2, 0, 1e-14], [1, 1, 0.]])
    F = np.array([[0, 1, 2], [0, 1, 3]])
    K = cotmatrix(V, F)
    assert np.isfinite(K.data).all()


def test_mass_sums_to_area():
    V, F = grid(curved=False, size=10.0)
    assert np.isclose(massmatrix(V, F).sum(), 100.0)


def _handles(V, step=7):
    return np.arange(0, len(V), step)


def test_basis_interpolates_handles_and_reproduces_translation(sheet):
    V, F = sheet
    H = _handles(V)
    for ks in (0.0, 1.0):
        B = shell_basis(V, F, H, k_stretch=ks)
        assert np.allclose(B[H], np.eye(len(H)))
        assert np.allclose(B.sum(axis=1), 1.0, atol=1e-8)


def test_basis_with_anchors_reproduces_translation_of_handles_and_anchors(sheet):
    V, F = sheet
    H = _handles(V)
    anchors = np.setdiff1d(np.arange(0, 12), H)
    B = shell_basis(V, F, H, anchors, columns=anchors)
    assert np.allclose(B.sum(axis=1), 1.0, atol=1e-8)
    assert np.allclose(B[anchors][:, len(H):], np.eye(len(anchors)))


def test_basis_matches_independent_sparse_solve(sheet):
    V, F = sheet
    H = _handles(V, 5)
    anchors = np.array([1, 2, 3])
    k_stretch, spacing = 0.7, 1.3
    B = shell_basis(V, F, H, anchors, k_stretch=k_stretch, spacing=spacing)
    rng = np.random.default_rng(0)
    uH = rng.normal(size=(len(H), 3))
    # independent: the full system with constraint rows replaced by identity rows, solved by SuperLU
    A = shell_operator(V, F, k_stretch, 1.0, spacing).tolil()
    rhs = np.zeros((len(V), 3))
    for rows, vals in ((H, uH), (anchors, np.zeros((len(anchors), 3)))):
        for r, val in zip(rows, vals):
            A.rows[r] = [r]
            A.data[r] = [1.0]
            rhs[r] = val
    u_ref = spla.spsolve(sp.csc_matrix(A), rhs)
    u = B @ uH
    assert np.linalg.norm(u - u_ref) / np.linalg.norm(u_ref) < 1e-5


def test_basis_is_scale_invariant(sheet):
    V, F = sheet
    H = _handles(V)
    B1 = shell_basis(V, F, H, k_stretch=2.0)
    B2 = shell_basis(10.0 * V, F, H, k_stretch=2.0)
    assert np.abs(B1 - B2).max() < 1e-8


def test_cholesky_factor_solves_multiple_rhs(sheet):
    V, F = sheet
    A = shell_operator(V, F, 1.0, 1.0) + sp.eye(len(V))
    b = np.random.default_rng(1).normal(size=(len(V), 4))
    x = CholeskyFactor(A).solve(b)
    assert np.abs(A @ x - b).max() < 1e-8


def test_large_scale_positions_batched(sheet):
    V, F = sheet
    H = _handles(V)
    B = shell_basis(V, F, H)
    u = np.random.default_rng(2).normal(size=(4, len(H), 3))
    out = large_scale_positions(V, B, u)
    assert out.shape == (4, len(V), 3)
    assert np.allclose(out[2], V + B @ u[2])


@pytest.mark.parametrize("backend", ["pardiso", "superlu"])
def test_solver_backends_agree_with_cholmod(sheet, backend):
    V, F = sheet
    H = _handles(V, 5)
    A = shell_operator(V, F, 0.3, 1.0).tocsc()
    free = np.setdiff1d(np.arange(len(V)), H)
    A_ff, rhs = A[free][:, free], A[free][:, H].toarray()
    ref = CholeskyFactor(A_ff, backends=("cholmod",))
    other = CholeskyFactor(A_ff, backends=(backend, "cholmod"))
    if other.backend != backend:
        pytest.skip(f"{backend} is not installed here")
    x_ref, x = ref.solve(rhs), other.solve(rhs)
    assert np.abs(x - x_ref).max() < 1e-9 * np.abs(x_ref).max()
    assert np.abs(other.solve(rhs[:, 2]) - x_ref[:, 2]).max() < 1e-9 * np.abs(x_ref).max()  # one right-hand side
    other.close()


def test_cholesky_factor_falls_back_when_a_backend_is_missing(sheet, monkeypatch):
    import facepipe.core.shell as shell

    def missing(*args):
        raise ImportError("not here")

    monkeypatch.setitem(shell._BACKENDS, "pardiso", missing)
    V, F = sheet
    A = shell_operator(V, F, 1.0, 1.0) + sp.eye(len(V))
    factor = CholeskyFactor(A)
    assert factor.backend == "cholmod"
    b = np.ones(len(V))
    assert np.abs(A @ factor.solve(b) - b).max() < 1e-8


def test_constrained_system_is_the_identity_at_the_constraints(sheet):
    V, F = sheet
    H = _handles(V, 5)
    anchors = np.array([1, 2, 3])
    A = shell_operator(V, F, 0.4, 1.0)
    free, constrained = constrained_split(len(V), H, anchors)
    U, R, rhs_rows = constrained_system(A, constrained, H)
    assert U.indices.dtype == np.int32 and abs(U - sp.triu(U)).max() == 0
    full = (U + sp.triu(U, k=1).T).toarray()
    # independent: the same blocks cut out by SciPy's indexing
    dense = A.toarray()
    ff = np.ix_(free, free)
    assert np.array_equal(np.triu(full[ff]), np.triu(dense[ff]))  # A's own entries, not recomputed
    assert np.array_equal(full[constrained][:, constrained], np.eye(constrained.sum()))
    assert not full[constrained][:, free].any() and not full[free][:, constrained].any()
    assert np.abs(R[free] + dense[np.ix_(free, H)]).max() < 1e-12 * np.abs(dense).max()
    assert np.array_equal(R[H], np.eye(len(H))) and not R[anchors].any()
    assert set(np.flatnonzero(np.abs(R).sum(axis=1))) <= set(rhs_rows)


@pytest.mark.parametrize("backend", ["pardiso", "cholmod", "superlu"])
def test_factor_of_an_upper_triangle_with_sparse_right_hand_sides(backend):
    V, F = grid(nx=30, ny=30)
    H = _handles(V, 97)  # a few handles: their rows are a small part of the system's
    A = shell_operator(V, F, 0.3, 1.0)
    _, constrained = constrained_split(len(V), H, None)
    U, R, rhs_rows = constrained_system(A, constrained, H)
    full = sp.csc_matrix(U + sp.triu(U, k=1).T)
    reference = spla.spsolve(full, R)
    factor = CholeskyFactor(U, backends=(backend,) if backend != "pardiso" else ("pardiso", "cholmod"),
                            upper=True, rhs_rows=rhs_rows)
    if factor.backend != backend:
        pytest.skip(f"{backend} is not installed here")
    if backend == "pardiso":
        assert len(rhs_rows) < len(V) / 4 and factor._solver._iparm[30] == 2  # the sparse solve is the one tested
    x = factor.solve(R)
    assert np.abs(x - reference).max() < 1e-9 * np.abs(reference).max()
    factor.close()
