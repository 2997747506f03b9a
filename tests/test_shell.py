import ctypes.util
import importlib.metadata
import importlib.util
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla

import facepipe.core.shell as shell
from facepipe.io.mesh_read import load_mesh
from facepipe.core.shell import (COT_LIMIT, MIN_ANGLE, CholeskyFactor, clamped_angles, constrained_split,
                                 constrained_system, cotmatrix, large_scale_positions, massmatrix, mkl_runtime_library,
                                 shell_basis, shell_operator, solve_shell_basis)
from tests.conftest import ICT, ROOT, grid, run_cli


def _mkl_installed() -> bool:
    """MKL is here (its wheel's metadata or its library): PARDISO must then work, and a broken
    binding fails the PARDISO tests instead of skipping them."""
    try:
        importlib.metadata.distribution("mkl")
        return True
    except importlib.metadata.PackageNotFoundError:
        return mkl_runtime_library() is not None


def _installed(backend: str) -> bool:
    if backend == "pardiso":
        return _mkl_installed()
    if backend == "cholmod":
        return importlib.util.find_spec("cholespy") is not None
    return True  # SciPy's SuperLU


def _factor_with(backend: str, A, **kwargs) -> CholeskyFactor:
    """A factor by ``backend`` alone; skip only where its library is not installed at all."""
    if not _installed(backend):
        pytest.skip(f"{backend} is not installed here")
    return CholeskyFactor(A, backends=(backend,), **kwargs)  # RuntimeError (a failure) where it is broken


def _plain_cotmatrix(V, F):
    """K from the unclamped cotangents, in the same order of operations as ``cotmatrix`` (so equal
    bit for bit where no angle is below MIN_ANGLE)."""
    c = [V[F[:, k]] for k in range(3)]
    cross = np.linalg.norm(np.cross(c[1] - c[0], c[2] - c[0]), axis=1)
    rows, cols, vals = [], [], []
    for k in range(3):
        i, j = (k + 1) % 3, (k + 2) % 3
        a, b = c[i] - c[k], c[j] - c[k]
        scale = np.einsum("ij,ij->i", a, a) + np.einsum("ij,ij->i", b, b)
        w = 0.5 * (np.einsum("ij,ij->i", a, b) / np.maximum(cross, 1e-12 * scale + 1e-300))
        rows += [F[:, i], F[:, j]]
        cols += [F[:, j], F[:, i]]
        vals += [-w, -w]
    off = sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(len(V), len(V)))
    return (off + sp.diags(-np.asarray(off.sum(axis=1)).ravel())).tocsr()


def _mesh_with_slivers():
    """A flat 8 × 8 grid with an edge split by a cap triangle (angles 1e-5, 1e-5, π − 2e-5), a needle
    (one angle 1e-7) hung on the boundary, a zero-area (collinear) and a coincident-corner triangle.
    Returns V, F and the indices of those four triangles."""
    V, F = grid(nx=8, ny=8, curved=False, size=7.0)  # spacing 1
    V = V.copy()
    # the first lower-left triangle's diagonal edge (a, c) and its two triangles (a, b, c), (a, c, d)
    a, b, c = F[0]
    d = next(f[2] for f in F if f[0] == a and f[1] == c)
    mid = 0.5 * (V[a] + V[c])
    toward_b = (V[b] - mid) / np.linalg.norm(V[b] - mid)
    half = 0.5 * np.linalg.norm(V[c] - V[a])
    m = len(V)
    V = np.vstack([V, mid + np.tan(1e-5) * half * toward_b])  # the cap's apex, just off the edge ac on b's side
    F = [list(f) for f in F if not (f[0] == a and f[1] == b and f[2] == c)]
    F += [[a, b, m], [m, b, c], [a, m, c]]  # (a, c, d) stays across the edge ac
    cap = len(F) - 1
    # a needle on the bottom boundary edge (0, 1): apex far below it, angle 1e-7 at the apex
    far = len(V)
    V = np.vstack([V, [0.5 * (V[0, 0] + V[1, 0]), V[0, 1] - 0.5 / np.tan(0.5e-7), 0.0]])
    F.append([0, 1, far])
    needle = len(F) - 1
    # a collinear triangle on the top boundary, and one with two corners at the same point
    top = np.flatnonzero(np.isclose(V[:, 1], V[:m, 1].max()))[:2]
    line = len(V)
    V = np.vstack([V, V[top[0]] + 2.0 * (V[top[1]] - V[top[0]])])  # on the line through top[0], top[1]
    F.append([top[0], top[1], line])
    flat = len(F) - 1
    twin = len(V)
    V = np.vstack([V, V[line]])  # the same point as vertex `line`
    F.append([top[1], line, twin])
    coincident = len(F) - 1
    return V, np.array(F), (cap, needle, flat, coincident)


def _element(V, face):
    K = cotmatrix(V, np.asarray([face])).toarray()
    return K[np.ix_(face, face)]


# --------------------------------------------------------------------------- cotangent Laplacian


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


def test_cotmatrix_of_a_quadratic_is_its_laplacian_times_the_area():
    # Δ(x² + y²) = 4: on a regular flat grid the cotangent Laplacian with barycentric areas gives it
    # exactly at every interior vertex; K = -L
    V, F = grid(curved=False)  # rectangular cells (10/11 × 10/9)
    K, M = cotmatrix(V, F), massmatrix(V, F)
    f = V[:, 0] ** 2 + V[:, 1] ** 2
    interior = (np.abs(V[:, 0]) < 4.9) & (np.abs(V[:, 1]) < 4.9)
    assert np.abs((K @ f / M)[interior] + 4.0).max() < 1e-12
    # on a square grid the weights inside are 1 on the cells' sides, 0 on their diagonals (cot 90°)
    V, F = grid(nx=6, ny=6, curved=False, size=5.0)
    K = cotmatrix(V, F).toarray()
    interior = (np.abs(V[:, 0]) < 2.4) & (np.abs(V[:, 1]) < 2.4)
    side = np.isclose(np.linalg.norm(V[:, None] - V[None], axis=-1), 1.0)[interior]
    rows = K[interior]
    assert np.abs(rows[side] + 1.0).max() < 1e-14 and np.abs(np.diag(K)[interior] - 4.0).max() < 1e-14
    assert np.abs(rows[~side & ~np.eye(len(V), dtype=bool)[interior]]).max() < 1e-14


def test_cotmatrix_clamps_degenerate_triangles_by_their_angles():
    # vertices 0, 1, 2 nearly on a line (angles ≈ 1e-14, π, 1e-14), and a right isosceles triangle
    V = np.array([[0, 0, 0], [1, 0, 0], [2, 0, 1e-14], [1, 1, 0.]])
    F = np.array([[0, 1, 2], [0, 1, 3]])
    K = cotmatrix(V, F).toarray()
    small = 0.5 * COT_LIMIT  # ½ cot MIN_ANGLE, on the edges opposite the two tiny angles
    large = -0.5 / np.tan(2 * MIN_ANGLE)  # ½ cot(π − 2 MIN_ANGLE), opposite the straight angle
    expected = {(0, 1): small + 0.5, (1, 2): small, (0, 2): large, (1, 3): 0.5, (0, 3): 0.0}
    for (i, j), w in expected.items():
        assert np.isclose(-K[i, j], w, rtol=1e-9, atol=1e-12), (i, j, K[i, j], w)
    assert np.linalg.eigvalsh(K).min() >= -1e-12 * np.abs(K).max()


def test_clamped_angles_are_a_triangles_and_only_move_the_small_ones():
    rng = np.random.default_rng(3)
    cases = np.array([[1e-5, 1e-5, np.pi - 2e-5], [1e-7, 0.5 * (np.pi - 1e-7), 0.5 * (np.pi - 1e-7)],
                      [0.0, np.pi, 0.0], [0.0, 0.0, 0.0], [5e-5, 1.0, np.pi - 1.0 - 5e-5]])
    out = clamped_angles(cases)
    assert np.allclose(out.sum(axis=1), np.pi, rtol=0, atol=1e-14)
    assert (out >= MIN_ANGLE).all() and (out <= np.pi - 2 * MIN_ANGLE + 1e-15).all()
    assert np.allclose(out[3], np.pi / 3)  # no angles at all: an equilateral triangle's
    assert np.array_equal(np.argsort(out[4]), np.argsort(cases[4]))  # the weights stay on their edges
    # the element matrix of any three such angles is positive semi-definite: Σ cot cot ≥ 0 (it is 1)
    angles = clamped_angles(rng.uniform(0, 1e-3, size=(1000, 3)) * [1, 1, 0] + [0, 0, np.pi - 1e-3])
    cot = 1 / np.tan(angles)
    pairs = cot[:, 0] * cot[:, 1] + cot[:, 1] * cot[:, 2] + cot[:, 2] * cot[:, 0]
    # (cot(π − s) carries the round-off of π − s, relative ~1e-12 for s ≥ 2e-4: the sum of products up
    # to 1e8 moves by ~1e-4, far from 0)
    assert np.abs(pairs - 1.0).max() < 1e-3


def test_cotmatrix_stays_positive_semidefinite_with_slivers():
    # clipping each cotangent at ±COT_LIMIT gave the cap triangle weights (5000, 5000, −5000): element
    # eigenvalues (−5000, 0, 15000), and an indefinite K and shell operator
    V, F, slivers = _mesh_with_slivers()
    for t in slivers:
        Ke = _element(V, F[t])
        assert np.isfinite(Ke).all()
        assert np.linalg.eigvalsh(Ke).min() >= -1e-12 * np.abs(Ke).max(), (t, np.linalg.eigvalsh(Ke))
    for face in F:
        Ke = _element(V, face)
        assert np.linalg.eigvalsh(Ke).min() >= -1e-12 * np.abs(Ke).max()
    K = cotmatrix(V, F)
    eig = np.linalg.eigvalsh(K.toarray())
    assert eig.min() >= -1e-12 * eig.max(), (eig.min(), eig.max())
    for k_stretch, k_bend in ((1.0, 0.0), (1.0, 1.0)):
        A = shell_operator(V, F, k_stretch, k_bend).toarray()
        eig = np.linalg.eigvalsh(0.5 * (A + A.T))
        assert eig.min() >= -1e-12 * eig.max(), (k_stretch, k_bend, eig.min(), eig.max())
    # the cap's apex stays tied to its neighbours: a shell with handles around it is solvable
    H = np.arange(0, len(V) - 3, 5)
    B = solve_shell_basis(V, F, H, k_stretch=1.0).B
    assert np.allclose(B.sum(axis=1), 1.0, atol=1e-8)


def test_cotmatrix_without_small_angles_is_the_plain_formula_bit_for_bit(sheet):
    meshes = [sheet, grid(curved=False)]
    if (ICT / "neutral.obj").is_file():  # the ICT kit's face: its largest cotangent is 22, no clamp
        mesh = load_mesh(ICT / "neutral.obj")
        meshes.append((mesh.vertices, mesh.faces))
    for V, F in meshes:
        K, reference = cotmatrix(V, F), _plain_cotmatrix(V, F)
        assert np.array_equal(K.indptr, reference.indptr) and np.array_equal(K.indices, reference.indices)
        assert np.array_equal(K.data, reference.data)


# --------------------------------------------------------------------------- mass


def test_mass_sums_to_area():
    V, F = grid(curved=False, size=10.0)
    assert np.isclose(massmatrix(V, F).sum(), 100.0, rtol=1e-14)


def test_mass_is_a_third_of_the_incident_areas():
    # a square grid of spacing 1 split into right triangles: an interior vertex touches 6 of area ½
    V, F = grid(nx=6, ny=6, curved=False, size=5.0)
    M = massmatrix(V, F)
    interior = (np.abs(V[:, 0]) < 2.4) & (np.abs(V[:, 1]) < 2.4)
    assert np.allclose(M[interior], 1.0, rtol=1e-14)
    # a bent sheet: the sum is the triangles' total area, computed by Heron's formula
    V, F = grid()
    a, b, c = (np.linalg.norm(V[F[:, i]] - V[F[:, j]], axis=1) for i, j in ((0, 1), (1, 2), (2, 0)))
    s = 0.5 * (a + b + c)
    assert np.isclose(massmatrix(V, F).sum(), np.sqrt(s * (s - a) * (s - b) * (s - c)).sum(), rtol=1e-12)


def test_the_shell_operator_shares_the_areas_of_the_cotangents_bit_for_bit(sheet):
    """The operator takes the mass from the triangle areas the cotangents computed: the same
    arithmetic as each alone."""
    V, F = sheet
    K = cotmatrix(V, F)
    M = massmatrix(V, F)
    assert np.array_equal(massmatrix(V, F, shell._cotmatrix_and_areas(V, F)[1]), M)
    parts = shell.ShellParts.of(V, F)
    assert abs(parts.K - K).max() == 0 and abs(parts.KMK - K @ sp.diags(1.0 / M) @ K).max() == 0


# --------------------------------------------------------------------------- the basis B


def _handles(V, step=7):
    return np.arange(0, len(V), step)


def test_basis_interpolates_handles_and_reproduces_translation(sheet):
    V, F = sheet
    H = _handles(V)
    for ks in (0.0, 1.0):
        B = shell_basis(V, F, H, k_stretch=ks)
        assert np.array_equal(B[H], np.eye(len(H)))
        assert np.abs(B.sum(axis=1) - 1.0).max() < 1e-10


def test_basis_with_anchors_reproduces_translation_of_handles_and_anchors(sheet):
    V, F = sheet
    H = _handles(V)
    anchors = np.setdiff1d(np.arange(0, 12), H)
    B = shell_basis(V, F, H, anchors, columns=anchors)
    assert np.abs(B.sum(axis=1) - 1.0).max() < 1e-10
    assert np.array_equal(B[anchors][:, len(H):], np.eye(len(anchors)))


def test_basis_reproduces_linear_fields_on_a_flat_sheet():
    # with the two outer rings of a flat sheet prescribed, -k_s Δu + k_b Δ²u = 0 holds for every
    # linear u on the free vertices, so B gives linear handle displacements back exactly: in-plane
    # rotations, stretches and shears, and out-of-plane tilts (linearised rotations)
    V, F = grid(nx=14, ny=12, curved=False)
    x, y = V[:, 0], V[:, 1]
    step = np.array([10 / 13, 10 / 11])
    ring = np.minimum((5 - np.abs(x)) / step[0], (5 - np.abs(y)) / step[1])
    H = np.union1d(np.flatnonzero(ring < 1.5), np.flatnonzero(ring > 1.5)[::9])
    u = np.stack([0.3 * x - 0.2 * y + 0.1, 0.2 * x + 0.05 * y, 0.4 * x - 0.7 * y + 2.0], axis=1)
    for ks in (0.0, 0.5):
        B = shell_basis(V, F, H, k_stretch=ks)
        assert np.abs(B @ u[H] - u).max() < 1e-10 * np.abs(u).max()


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
    assert np.linalg.norm(u - u_ref) / np.linalg.norm(u_ref) < 1e-10


def test_basis_is_scale_invariant(sheet):
    V, F = sheet
    H = _handles(V)
    B1 = shell_basis(V, F, H, k_stretch=2.0)
    B2 = shell_basis(10.0 * V, F, H, k_stretch=2.0)
    assert np.abs(B1 - B2).max() < 1e-8


def test_solve_shell_basis_names_its_solver(sheet, monkeypatch):
    V, F = sheet
    H = _handles(V)
    solved = solve_shell_basis(V, F, H)
    expected = next(b for b in ("pardiso", "cholmod", "superlu") if _installed(b))
    assert solved.solver == expected and solved.passed_over == {}
    assert np.array_equal(solved.B, shell_basis(V, F, H))
    monkeypatch.setitem(shell._BACKENDS, "pardiso", _missing)
    fallback = solve_shell_basis(V, F, H)
    assert fallback.solver != "pardiso" and fallback.passed_over == {"pardiso": "ImportError: not here"}
    assert solve_shell_basis(V, F, np.arange(len(V))).solver is None  # nothing free, nothing factored


def test_large_scale_positions_batched(sheet):
    V, F = sheet
    H = _handles(V)
    B = shell_basis(V, F, H)
    u = np.random.default_rng(2).normal(size=(4, len(H), 3))
    out = large_scale_positions(V, B, u)
    assert out.shape == (4, len(V), 3)
    assert np.allclose(out[2], V + B @ u[2], rtol=0, atol=1e-12)


# --------------------------------------------------------------------------- sparse solvers


def _missing(*args, **options):
    raise ImportError("not here")


@pytest.mark.parametrize("backend", ["pardiso", "superlu"])
def test_solver_backends_agree_with_cholmod(sheet, backend):
    V, F = sheet
    H = _handles(V, 5)
    A = shell_operator(V, F, 0.3, 1.0).tocsc()
    free = np.setdiff1d(np.arange(len(V)), H)
    A_ff, rhs = A[free][:, free], A[free][:, H].toarray()
    ref = _factor_with("cholmod", A_ff)
    other = _factor_with(backend, A_ff)
    assert other.backend == backend
    x_ref, x = ref.solve(rhs), other.solve(rhs)
    assert np.abs(x - x_ref).max() < 1e-9 * np.abs(x_ref).max()
    assert np.abs(other.solve(rhs[:, 2]) - x_ref[:, 2]).max() < 1e-9 * np.abs(x_ref).max()  # one right-hand side
    other.close()


@pytest.mark.parametrize("backend", ["pardiso", "cholmod", "superlu"])
def test_cholesky_factor_solves_multiple_rhs(sheet, backend):
    V, F = sheet
    A = shell_operator(V, F, 1.0, 1.0) + sp.eye(len(V))
    b = np.random.default_rng(1).normal(size=(len(V), 4))
    x = _factor_with(backend, A).solve(b)
    assert np.abs(x - spla.spsolve(A.tocsc(), b)).max() < 1e-10 * np.abs(x).max()


@pytest.mark.parametrize("backend", ["pardiso", "cholmod", "superlu"])
def test_overwrite_b_solves_the_same_and_leaves_the_caller_a_result(sheet, backend):
    """overwrite_b: PARDISO writes the solution over a Fortran-ordered float64 b (the same numbers
    bit for bit as into a fresh array); b of another layout or type, and other backends, leave
    b as it was. The result is returned either way."""
    V, F = sheet
    A = shell_operator(V, F, 1.0, 1.0) + sp.eye(len(V))
    factor = _factor_with(backend, A)
    b = np.asfortranarray(np.random.default_rng(3).normal(size=(len(V), 5)))
    expected = factor.solve(b.copy(order="F"))
    given = b.copy(order="F")
    x = factor.solve(given, overwrite_b=True)
    assert np.array_equal(x, expected)
    assert np.shares_memory(x, given) == (backend == "pardiso")
    c_order = np.ascontiguousarray(b)  # another layout: a copy is solved, b kept
    x = factor.solve(c_order, overwrite_b=True)
    assert np.array_equal(x, expected) and np.array_equal(c_order, b)
    one = b[:, 0].copy()  # one right-hand side (PARDISO's numbers for one column differ from a block's in round-off)
    assert np.array_equal(factor.solve(one.copy(), overwrite_b=True), factor.solve(one))
    assert np.array_equal(factor.solve(b), expected) and factor.solve(b) is not b  # without it b is kept
    factor.close()


@pytest.mark.parametrize("backend", ["pardiso", "cholmod", "superlu"])
def test_refactored_matrix_of_the_same_pattern_solves_as_a_fresh_factor(sheet, backend):
    """refactor: another matrix of the pattern (PARDISO keeps its analysis), then back; a matrix of
    another pattern is factored afresh."""
    V, F = sheet
    K = shell_operator(V, F, 1.0, 0.0)
    b = np.random.default_rng(2).normal(size=(len(V), 3))
    factor = _factor_with(backend, sp.eye(len(V)) + 0.5 * K)
    for A in (sp.eye(len(V)) + 3.0 * K, sp.eye(len(V)) + 0.5 * K, shell_operator(V, F, 1.0, 1.0) + sp.eye(len(V))):
        factor.refactor(A)
        assert factor.backend == backend
        x = factor.solve(b)
        assert np.abs(x - spla.spsolve(A.tocsc(), b)).max() < 1e-10 * np.abs(x).max()
    factor.close()


def test_cholesky_factor_falls_back_when_a_backend_is_missing(sheet, monkeypatch):
    monkeypatch.setitem(shell._BACKENDS, "pardiso", _missing)
    V, F = sheet
    A = shell_operator(V, F, 1.0, 1.0) + sp.eye(len(V))
    factor = CholeskyFactor(A, backends=("pardiso", "cholmod", "superlu"))
    assert factor.backend == ("cholmod" if _installed("cholmod") else "superlu")
    assert factor.passed_over["pardiso"] == "ImportError: not here"
    b = np.ones(len(V))
    assert np.abs(A @ factor.solve(b) - b).max() < 1e-8
    monkeypatch.setitem(shell._BACKENDS, "superlu", _missing)
    monkeypatch.setitem(shell._BACKENDS, "cholmod", _missing)
    with pytest.raises(RuntimeError, match="pardiso: ImportError: not here"):
        CholeskyFactor(A)


def test_mkl_found_from_its_wheel_without_pypardiso(monkeypatch, tmp_path):
    if not _mkl_installed():
        pytest.skip("MKL is not installed here")
    # neither the environment's lib folder, nor pypardiso, nor a search of the system: the wheel's own
    # file list must find the library
    monkeypatch.setattr(sys, "prefix", str(tmp_path))
    monkeypatch.setattr(shell.site, "USER_BASE", str(tmp_path), raising=False)
    monkeypatch.setitem(sys.modules, "pypardiso", None)
    monkeypatch.setitem(sys.modules, "pypardiso.pardiso_wrapper", None)
    monkeypatch.delenv("PYPARDISO_MKL_RT", raising=False)

    def no_search(name):
        raise AssertionError("find_library forks ldconfig and a compiler: not before the wheel's files")

    monkeypatch.setattr(ctypes.util, "find_library", no_search)
    monkeypatch.setattr(shell, "_PARDISO_FN", None)
    assert shell._mkl_pardiso() is not None
    wheel = {f.locate().resolve() for f in importlib.metadata.files("mkl") or []}
    assert Path(mkl_runtime_library()).resolve() in wheel


def test_pardiso_without_importing_pypardiso():
    if not _mkl_installed():
        pytest.skip("MKL is not installed here")
    code = ("import sys, numpy as np, scipy.sparse as sp\n"
            "from facepipe.core.shell import CholeskyFactor\n"
            "f = CholeskyFactor(sp.eye(5, format='csr') * 2.0, backends=('pardiso',))\n"
            "assert np.allclose(f.solve(np.ones(5)), 0.5)\n"
            "assert 'pypardiso' not in sys.modules, 'pypardiso imported'\n")
    subprocess.run([sys.executable, "-c", code], check=True, cwd=ROOT)  # this checkout's facepipe


@pytest.mark.parametrize("given, expected", [(None, "0"), ("50", "50")])
def test_pardiso_threads_sleep_when_idle_unless_the_user_says(given, expected):
    """MKL's OpenMP threads read KMP_BLOCKTIME when they start: facepipe sets it to 0 before MKL
    loads (idle threads sleep rather than spin beside the bake's other work); a user's value stands."""
    if not _mkl_installed():
        pytest.skip("MKL is not installed here")
    env = {k: v for k, v in os.environ.items() if k != "KMP_BLOCKTIME"}
    if given is not None:
        env["KMP_BLOCKTIME"] = given
    code = ("import os, numpy as np, scipy.sparse as sp\n"
            "from facepipe.core.shell import CholeskyFactor\n"
            "f = CholeskyFactor(sp.eye(5, format='csr') * 2.0, backends=('pardiso',))\n"
            "assert np.allclose(f.solve(np.ones(5)), 0.5)\n"
            "print(os.environ['KMP_BLOCKTIME'])\n")
    out = subprocess.run([sys.executable, "-c", code], check=True, cwd=ROOT, env=env, capture_output=True, text=True)
    assert out.stdout.strip() == expected


def test_constrained_system_is_the_identity_at_the_constraints(sheet):
    V, F = sheet
    H = _handles(V, 5)
    anchors = np.array([1, 2, 3])
    A = shell_operator(V, F, 0.4, 1.0)
    free, constrained = constrained_split(len(V), H, anchors)
    U, R = constrained_system(A, constrained, H)
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


@pytest.mark.parametrize("backend", ["pardiso", "cholmod", "superlu"])
def test_factor_of_an_upper_triangle_with_the_constrained_right_hand_sides(backend):
    V, F = grid(nx=30, ny=30)
    H = _handles(V, 97)  # a few handles: their rows are a small part of the system's
    A = shell_operator(V, F, 0.3, 1.0)
    _, constrained = constrained_split(len(V), H, None)
    U, R = constrained_system(A, constrained, H)
    full = sp.csc_matrix(U + sp.triu(U, k=1).T)
    reference = spla.spsolve(full, R)
    factor = _factor_with(backend, U, upper=True)
    x = factor.solve(R)
    assert np.abs(x - reference).max() < 1e-9 * np.abs(reference).max()
    factor.close()


# --------------------------------------------------------------------------- the solver on record


def test_fit_and_model_record_the_shell_solver(tmp_path, monkeypatch, capsys):
    rig = tmp_path / "rig"
    assert run_cli("sample", rig, "--vertices", 2000, "--examples", 6, "--frames", 4, "--markers", 30, "-q") == 0
    expected = next(b for b in ("pardiso", "cholmod", "superlu") if _installed(b))
    assert run_cli("fit", rig / "sample.toml", "-o", tmp_path / "fit.npz", "-v") == 0
    report = json.loads((tmp_path / "fit.json").read_text())
    assert report["shell_solver"] == expected and report["shell_solver_passed_over"] == {}
    assert f"shell solver: {expected}" in capsys.readouterr().out
    # a fallback is on record, with the reason, in the fit report, the model and --verbose
    monkeypatch.setitem(shell._BACKENDS, "pardiso", _missing)
    assert run_cli("fit", rig / "sample.toml", "-o", tmp_path / "fallback.npz", "-q") == 0
    report = json.loads((tmp_path / "fallback.json").read_text())
    assert report["shell_solver"] not in (None, "pardiso")
    assert report["shell_solver_passed_over"] == {"pardiso": "ImportError: not here"}
    capsys.readouterr()
    assert run_cli("bake", tmp_path / "fallback.npz", "-o", tmp_path / "model.npz", "-v") == 0
    assert f"shell solver: {report['shell_solver']}" in capsys.readouterr().out
    from facepipe.io.model_file import load_model

    assert load_model(tmp_path / "model.npz").meta["shell"]["solver"] == report["shell_solver"]


@pytest.mark.parametrize("k_stretch, anchored", [(0.0, True), (3.0, False)])
def test_shell_displacements_of_a_few_poses_equal_the_basis_times_the_handles(k_stretch, anchored):
    """Solving the shell for a few poses' right-hand sides gives B · u_H, without forming B."""
    vertices, faces = grid(16, 14)
    rng = np.random.default_rng(3)
    handles = rng.choice(len(vertices), 20, replace=False)
    anchors = np.setdiff1d(np.arange(0, len(vertices), 16), handles) if anchored else None
    u = rng.normal(scale=0.2, size=(4, len(handles), 3))
    B = shell.shell_basis(vertices, faces, handles, anchors, k_stretch=k_stretch)
    got = shell.shell_displacements(vertices, faces, handles, anchors, u, k_stretch=k_stretch)
    parts = shell.ShellParts.of(vertices, faces)  # the products made once, the same operator
    again = shell.shell_displacements(vertices, faces, handles, anchors, u, k_stretch=k_stretch, parts=parts)
    np.testing.assert_array_equal(again, got)
    A = shell.shell_operator(vertices, faces, k_stretch, 1.0, shell.marker_spacing(vertices, handles))
    assert (parts.operator(k_stretch, 1.0, shell.marker_spacing(vertices, handles)) != A).nnz == 0
    np.testing.assert_allclose(got, np.einsum("vh,ehc->evc", B, u), rtol=0, atol=1e-12)
    np.testing.assert_array_equal(got[:, handles], u)  # the handles hold their prescribed motion
    if anchored:
        assert not got[:, anchors].any()
