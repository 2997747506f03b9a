"""Large-scale deformation: a linear thin shell constrained at the marker handles.

Bickel et al. 2008, §4: minimise stretch + bending, -k_s Δu + k_b Δ²u = 0, with the
displacements u prescribed at the handle vertices (the markers) and held at zero at
the anchors (skull vertices). The system is linear in the handle displacements, so
the solve is precomputed once as B = -A_ff⁻¹ A_fH and every frame is u = B · u_H.

Discretisation: Δ = M⁻¹ L with the cotangent Laplacian L and the lumped mass M.
Multiplying by M gives the symmetric positive semi-definite operator
A = k_s K + k_b K M⁻¹ K with K = -L.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import fnmatch
import glob
import importlib.metadata
import os
import site
import sys
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree
import scipy.sparse.linalg as spla

# A near-degenerate triangle (an angle θ → 0) would put an unbounded weight cot θ on one edge
# and ruin the factorisation's conditioning, so no angle is taken below MIN_ANGLE, where
# cot θ = COT_LIMIT. The clamp acts on a triangle's angles, not on its cotangents one by one:
# a triangle's element matrix Σ_k ½ cot θ_k (e_i − e_j)(e_i − e_j)ᵀ is positive semi-definite
# exactly when cot θ_0 cot θ_1 + cot θ_1 cot θ_2 + cot θ_2 cot θ_0 ≥ 0 (with a positive sum), and
# that sum is 1 for any three angles in (0, π) that add up to π. Cotangents clipped one by one
# break it: a cap triangle with angles (1e-5, 1e-5, π − 2e-5) had cotangents (1e4, 1e4, −1e4)
# and the element eigenvalues (−5000, 0, 15000), an indefinite K. So the small angles are
# raised to MIN_ANGLE and the others lowered to keep the sum π: the weights are those of a
# real triangle (angles, not lengths, set them), its element matrix is positive semi-definite
# and so is K (in floating point the sum of products, up to 1e8 each, is 1 within ~1e-4: the
# round-off of π − 2 MIN_ANGLE, nowhere near 0). A triangle without a small angle takes no
# part: its weights are the plain cotangents, bit for bit (the ICT kit's largest is 22).
COT_LIMIT = 1e4
MIN_ANGLE = float(np.arctan(1.0 / COT_LIMIT))


def cotmatrix(vertices: np.ndarray, faces: np.ndarray) -> sp.csr_matrix:
    """Cotangent stiffness matrix K = -L (positive semi-definite, rows sum to zero).

    Parameters
    ----------
    vertices : (V, 3) float, any length unit.
    faces : (T, 3) int triangles.

    Returns
    -------
    K : (V, V) scipy.sparse.csr_matrix float64, dimensionless.
        K_ij = -(cot α_ij + cot β_ij) / 2 for an edge ij, K_ii = -Σ_j K_ij.

    Example
    -------
    >>> V = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0.]]); F = np.array([[0, 1, 2]])
    >>> np.allclose(cotmatrix(V, F).sum(axis=1), 0)
    True
    """
    return _cotmatrix_and_areas(vertices, faces)[0]


def _cotmatrix_and_areas(vertices: np.ndarray, faces: np.ndarray) -> tuple[sp.csr_matrix, np.ndarray]:
    """:func:`cotmatrix` and each triangle's |(b − a) × (c − a)| (twice its area), which it
    computes on the way (:func:`massmatrix` takes them rather than gathering the corners again)."""
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    n = vertices.shape[0]
    corner = [vertices[faces[:, k]] for k in range(3)]
    # |a × b| is twice the triangle's area at every corner: one cross product per triangle
    cross = np.linalg.norm(np.cross(corner[1] - corner[0], corner[2] - corner[0]), axis=1)
    cots, dots = [], []
    for k in range(3):
        # the angle at corner k is opposite the edge (i, j)
        i, j = (k + 1) % 3, (k + 2) % 3
        a = corner[i] - corner[k]
        b = corner[j] - corner[k]
        dot = np.einsum("ij,ij->i", a, b)
        scale = np.einsum("ij,ij->i", a, a) + np.einsum("ij,ij->i", b, b)
        cots.append(dot / np.maximum(cross, 1e-12 * scale + 1e-300))
        dots.append(dot)
    cot = np.stack(cots, axis=1)  # (T, 3)
    # an angle below MIN_ANGLE shows as a cotangent above COT_LIMIT (an angle near π leaves the
    # other two below it); only those triangles are recomputed
    small = np.flatnonzero((cot > COT_LIMIT).any(axis=1))
    if len(small):
        angles = np.arctan2(cross[small, None], np.stack(dots, axis=1)[small])
        cot[small] = 1.0 / np.tan(clamped_angles(angles))
    rows, cols, vals = [], [], []
    for k in range(3):
        i, j = (k + 1) % 3, (k + 2) % 3
        w = 0.5 * cot[:, k]
        rows += [faces[:, i], faces[:, j]]
        cols += [faces[:, j], faces[:, i]]
        vals += [-w, -w]
    rows = np.concatenate(rows)
    cols = np.concatenate(cols)
    vals = np.concatenate(vals)
    off = sp.csr_matrix((vals, (rows, cols)), shape=(n, n))  # duplicates (an edge's two triangles) summed
    diag = -np.asarray(off.sum(axis=1)).ravel()
    return (off + sp.diags(diag)).tocsr(), cross


def clamped_angles(angles: np.ndarray) -> np.ndarray:
    """A triangle's angles with none below MIN_ANGLE and their sum π (see COT_LIMIT).

    Parameters
    ----------
    angles : (T, 3) angles in radians, each in [0, π] (of a near-degenerate triangle their
        sum may be off π; with coincident corners all three may be 0).

    Returns
    -------
    (T, 3) angles in [MIN_ANGLE, π − 2 MIN_ANGLE] adding up to π: each raised to MIN_ANGLE, then
    the excesses over MIN_ANGLE scaled to share π − 3 MIN_ANGLE. The order of the angles is
    kept, so the weights stay on the same edges. A triangle with no excess at all (every corner
    coincident with another) gets the equilateral triangle's angles.

    Example
    -------
    >>> a = clamped_angles(np.array([[1e-5, 1e-5, np.pi - 2e-5]]))
    >>> bool(np.isclose(a.sum(), np.pi)) and bool(np.all(a >= MIN_ANGLE))
    True
    """
    excess = np.maximum(np.asarray(angles, dtype=np.float64), MIN_ANGLE) - MIN_ANGLE
    total = excess.sum(axis=1, keepdims=True)
    share = np.divide(excess, total, out=np.full_like(excess, 1.0 / 3.0), where=total > 0)
    return MIN_ANGLE + share * (np.pi - 3.0 * MIN_ANGLE)


def massmatrix(vertices: np.ndarray, faces: np.ndarray, double_areas: np.ndarray | None = None) -> np.ndarray:
    """Lumped (barycentric) vertex areas: a third of the area of each incident triangle.

    Barycentric lumping stays positive on obtuse triangles, where the Voronoi areas
    of the mixed scheme need special cases.

    Parameters
    ----------
    vertices : (V, 3) float; faces : (T, 3) int.
    double_areas : (T,) |(b − a) × (c − a)| of each triangle, if at hand (the same arithmetic).

    Returns
    -------
    mass : (V,) float64 in length² units, floored at a tiny fraction of the mean so
        that a vertex only touched by degenerate triangles does not divide by zero.
    """
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    if double_areas is None:
        double_areas = np.linalg.norm(np.cross(vertices[faces[:, 1]] - vertices[faces[:, 0]],
                                               vertices[faces[:, 2]] - vertices[faces[:, 0]]), axis=1)
    area = 0.5 * double_areas
    mass = np.bincount(faces.ravel(), weights=np.repeat(area / 3.0, 3), minlength=vertices.shape[0])
    floor = 1e-8 * max(float(mass.mean()), 1e-300)
    return np.maximum(mass, floor)


def marker_spacing(vertices: np.ndarray, handles: np.ndarray) -> float:
    """Mean distance from each handle to its nearest other handle (length units)."""

    points = np.asarray(vertices, dtype=np.float64)[np.asarray(handles)]
    if len(points) < 2:
        return 1.0
    dist, _ = cKDTree(points).query(points, k=2)
    return float(dist[:, 1].mean())


def shell_operator(vertices: np.ndarray, faces: np.ndarray, k_stretch: float, k_bend: float,
                   spacing: float = 1.0) -> sp.csr_matrix:
    """The symmetric shell operator A = (k_stretch / h²) K + k_bend K M⁻¹ K.

    ``k_stretch`` is relative to the marker spacing ``h``: K M⁻¹ K scales as 1/length²
    while K is scale-free, so dividing k_stretch by h² makes the same value mean the
    same trade-off on any mesh size and marker density.

    Returns
    -------
    A : (V, V) csr_matrix float64.
    """
    if not k_bend:  # K M⁻¹ K is not needed
        K = cotmatrix(vertices, faces)
        return ((k_stretch / spacing**2) * K).tocsr() if k_stretch else sp.csr_matrix(K.shape)
    return ShellParts.of(vertices, faces).operator(k_stretch, k_bend, spacing)


@dataclass(frozen=True)
class ShellParts:
    """The parts of the shell operator that do not depend on the stiffnesses: the cotangent
    Laplacian K and K M⁻¹ K. Validation factors the shell for several k_stretch; the sparse
    products are made once."""

    K: sp.csr_matrix
    KMK: sp.csr_matrix

    @classmethod
    def of(cls, vertices: np.ndarray, faces: np.ndarray) -> "ShellParts":
        K, double_areas = _cotmatrix_and_areas(vertices, faces)
        Minv = sp.diags(1.0 / massmatrix(vertices, faces, double_areas))
        return cls(K, K @ Minv @ K)

    def operator(self, k_stretch: float, k_bend: float, spacing: float = 1.0) -> sp.csr_matrix:
        """A = (k_stretch / h²) K + k_bend K M⁻¹ K (see :func:`shell_operator`), the same arithmetic."""
        terms = []
        if k_bend:
            terms.append(k_bend * self.KMK)
        if k_stretch:
            terms.append((k_stretch / spacing**2) * self.K)
        if not terms:
            return sp.csr_matrix(self.K.shape)
        return (terms[0] + terms[1] if len(terms) == 2 else terms[0]).tocsr()


class CholeskyFactor:
    """A sparse Cholesky factorisation of a symmetric positive definite matrix.

    Backends, the first that loads:

    * ``pardiso``: Intel MKL PARDISO (the ``mkl`` wheel that ``pypardiso`` pulls in; x86-64),
      called directly (see :class:`_Pardiso`);
    * ``cholmod``: CHOLMOD through cholespy (ships it in a wheel, any platform);
    * ``superlu``: SciPy's SuperLU.

    Why PARDISO first: cholespy's CHOLMOD build orders with AMD (no METIS) and factors with one
    thread; PARDISO orders by METIS nested dissection and factors in parallel, several times
    faster at the paper's scale (``make bench`` times the bake's phases), by the same exact
    Cholesky method (B agrees with CHOLMOD's to round-off). SuperLU is an LU without symmetry
    and a poor ordering, far slower on large meshes. ``solve`` takes one or many right-hand
    sides.
    """

    def __init__(self, A: sp.spmatrix, backends: tuple[str, ...] = ("pardiso", "cholmod", "superlu"),
                 upper: bool = False, single: bool = False):
        """``upper``: A holds only the upper triangle of the matrix (what PARDISO reads, so it
        is not cut out again). ``single``: PARDISO factors and solves in single precision
        (float32: half the memory traffic, several times quicker for many right-hand sides;
        solutions to ~1e-6 relative) for filters whose results are float32 anyway; the other
        backends stay in double precision. :attr:`single` says which was used."""
        A = sp.csr_matrix(A)
        self.single = False
        self.n = A.shape[0]
        self._solver = None
        self.backend: str | None = None
        # backend -> why it was passed over (not installed, or refused the matrix): the fallback
        # is reported, never silent
        self.passed_over: dict[str, str] = {}
        full = None
        for backend in backends:
            try:
                if backend == "pardiso":
                    self._solver = _BACKENDS[backend](A if upper else _upper_triangle(A), single=single)
                    self.single = single
                else:
                    if full is None:
                        full = A + sp.triu(A, k=1, format="csr").T if upper else A
                    self._solver = _BACKENDS[backend](sp.csr_matrix(full))
            except (ImportError, OSError, _PardisoError) as exc:
                self.passed_over[backend] = f"{exc.__class__.__name__}: {exc}"
                continue  # the next one
            self.backend = backend
            break
        if self._solver is None:
            why = "; ".join(f"{b}: {reason}" for b, reason in self.passed_over.items())
            raise RuntimeError(f"no sparse solver among {backends} could factor the matrix ({why})")

    def solve(self, b: np.ndarray, overwrite_b: bool = False) -> np.ndarray:
        """The solution of A x = b (float32 from a single-precision factor, else float64).

        ``overwrite_b``: b is not needed afterwards, and PARDISO may write the solution over it
        where it is a Fortran-ordered array of the factor's type (many right-hand sides: the
        shell basis's 89 columns at 530k vertices are 0.38 GB that need not be written a second
        time); the result is returned either way, and other backends leave b as it was."""
        return self._solver.solve(np.asarray(b, dtype=np.float32 if self.single else np.float64), overwrite_b)

    def refactor(self, A: sp.spmatrix, upper: bool = False) -> None:
        """Factor another matrix in place of this one (``upper`` as for the constructor). Where it
        has the same sparsity pattern PARDISO keeps its analysis (the ordering and the symbolic
        factor: most of a factorisation's time on a large mesh) and only factors the new values;
        otherwise, and on the other backends, it factors afresh."""
        A = sp.csr_matrix(A)
        if self.backend == "pardiso":
            U = A if upper else _upper_triangle(A)
            U.sort_indices()
            if self._solver.same_pattern(U):
                self._solver.refactor(U.data)
                return
        self.close()
        self.__init__(A, backends=(self.backend,), upper=upper, single=self.single)

    def close(self) -> None:
        """Free the factor now (PARDISO holds it outside Python's memory)."""
        close = getattr(self._solver, "close", None)
        if close is not None:
            close()


class _Cholmod:
    def __init__(self, A: sp.csr_matrix):
        import cholespy  # lazily: the fallback where PARDISO is not available

        coo = A.tocoo()
        self._solver = cholespy.CholeskySolverD(A.shape[0], coo.row.astype(np.int32), coo.col.astype(np.int32),
                                                coo.data.astype(np.float64), cholespy.MatrixType.COO)

    def solve(self, b: np.ndarray, overwrite_b: bool = False) -> np.ndarray:  # (b is never overwritten here)
        b = np.ascontiguousarray(b)
        x = np.zeros_like(b)
        self._solver.solve(b, x)
        return x


class _SuperLU:
    def __init__(self, A: sp.csr_matrix):

        self._solver = spla.splu(A.tocsc(), permc_spec="MMD_AT_PLUS_A")

    def solve(self, b: np.ndarray, overwrite_b: bool = False) -> np.ndarray:  # (b is never overwritten here)
        return self._solver.solve(b)


class _PardisoError(RuntimeError):
    pass


# MKL's single dynamic library, by platform: Linux, Windows, macOS (the mkl wheel's names)
_MKL_RT_PATTERNS = ("libmkl_rt.so*", "mkl_rt*.dll", "libmkl_rt*.dylib")


def mkl_runtime_library() -> str | None:
    """The path of MKL's runtime library ``mkl_rt``, or None where MKL is not installed.

    Looked for, in order: among the files the ``mkl`` distribution installed (its metadata's
    file list, wherever pip put it: the environment, the user site); in the environment's and
    the user base's library folders (``lib``, ``Library/bin``: conda, other installers); at
    the path in ``PYPARDISO_MKL_RT``; by ``ctypes.util.find_library``. The last runs ldconfig
    and a C compiler in a child process (forked from this one, by then gigabytes large in a
    bake), so it only comes where nothing else found the library; pypardiso is not imported
    for the same reason (its import runs that search).
    """
    try:
        files = importlib.metadata.files("mkl") or []
    except importlib.metadata.PackageNotFoundError:
        files = []
    for pattern in _MKL_RT_PATTERNS:
        found = sorted(str(f.locate()) for f in files if fnmatch.fnmatch(f.name, pattern))
        found = [path for path in found if os.path.isfile(path)]
        if found:
            return os.path.normpath(found[0])
    for base in filter(None, (sys.prefix, site.USER_BASE)):
        for folder in ("lib", os.path.join("Library", "bin")):
            for pattern in _MKL_RT_PATTERNS:
                found = sorted(glob.glob(os.path.join(base, folder, pattern)))
                if found:
                    return found[0]
    explicit = os.environ.get("PYPARDISO_MKL_RT")
    if explicit and os.path.isfile(explicit):
        return explicit
    return ctypes.util.find_library("mkl_rt")


def idle_threads_sleep(environ=os.environ) -> None:
    """Let MKL's OpenMP threads sleep as soon as they are idle (``KMP_BLOCKTIME=0``) unless the
    user chose otherwise; read once, when MKL starts its threads.

    A bake factors the shell beside other work: the examples' reader, the geodesics on the
    OpenCL device, the fit's own threads. With OpenMP's default, each idle MKL thread spins for
    200 ms at every wait, taking a core that work needs: measured on a two-core machine, a
    530k-vertex bake's median 21.5 → 20.1 s and 1–3 s less CPU (eight interleaved pairs); a
    per-frame solve loop, where the threads would stay warm, was not measurably slower.
    """
    environ.setdefault("KMP_BLOCKTIME", "0")


def _mkl_pardiso():
    """MKL's ``pardiso`` entry point (ImportError where MKL is not installed)."""
    global _PARDISO_FN
    if _PARDISO_FN is None:
        name = mkl_runtime_library()
        if name is None:
            raise ImportError("MKL's runtime library (mkl_rt) is not installed here")
        idle_threads_sleep()
        lib = ctypes.CDLL(name)  # our own handle: its argtypes are ours
        try:
            fn = lib.pardiso
        except AttributeError:
            raise OSError(f"{name} has no pardiso entry point") from None
        fn.restype = None
        fn.argtypes = [ctypes.c_void_p] * 16
        _PARDISO_FN = fn
    return _PARDISO_FN


_PARDISO_FN = None


class _Pardiso:
    """MKL PARDISO for a real symmetric positive definite matrix (mtype 2), called directly.

    pypardiso's own solver class treats every matrix as unsymmetric (an LU, twice the work),
    refines each solution iteratively (default iparm), and copies and hashes the matrix on
    each call. Here: the upper triangle, Cholesky,
    METIS nested dissection (iparm[1] = 3, the parallel version), the two-level parallel factorisation
    (iparm[23] = 1), no refinement, all right-hand sides in one call, 0-based indices.
    """

    MTYPE = 2  # real symmetric positive definite

    def __init__(self, U: sp.csr_matrix, single: bool = False):
        """``U``: the matrix's upper triangle (:func:`_upper_triangle`); ``single``: see
        :class:`CholeskyFactor`."""
        self._fn = _mkl_pardiso()
        U.sort_indices()
        self.n = U.shape[0]
        self._ia = U.indptr.astype(np.int32)
        self._ja = U.indices.astype(np.int32)
        self._dtype = np.float32 if single else np.float64
        self._a = np.ascontiguousarray(U.data, dtype=self._dtype)
        self._pt = np.zeros(64, dtype=np.int64)  # PARDISO's handle: opaque, must stay put
        self._iparm = np.zeros(64, dtype=np.int32)
        iparm = self._iparm
        iparm[0] = 1    # these settings, not the defaults
        iparm[1] = 3    # METIS nested dissection, its OpenMP version (the same fill, ~30 % quicker on two cores)
        iparm[7] = 0    # no iterative refinement (a Cholesky factor needs none)
        iparm[9] = 8    # pivot perturbation 1e-8 (unused for SPD)
        iparm[17] = -1  # report the factor's non-zeros
        iparm[23] = 1   # two-level parallel factorisation
        iparm[34] = 1   # 0-based indices
        if single:
            iparm[27] = 1  # single precision: matrix, factor, right-hand sides and solutions in float32
            iparm[24] = 2  # the solve parallel over right-hand sides too (many of them here: frames × xyz)
        # (PARDISO's sparse right-hand sides, iparm[30], skip most of the shell basis's forward
        # substitution, but the ordering they impose costs the factor more fill than they save:
        # at 530k vertices 86M non-zeros against 76M, factor and solve 0.3 s slower)
        self._perm = np.zeros(1, dtype=np.int32)  # (no user ordering)
        self._open = True
        try:
            self._call(12, np.zeros(1, self._dtype), np.zeros(1, self._dtype), 1)  # analysis + factorisation
        except _PardisoError:
            self.close()
            raise
        self.factor_nonzeros = int(iparm[17])

    def _call(self, phase: int, b: np.ndarray, x: np.ndarray, nrhs: int) -> None:
        err = ctypes.c_int32(0)

        def i32(v):
            return ctypes.byref(ctypes.c_int32(v))

        self._fn(self._pt.ctypes.data, i32(1), i32(1), i32(self.MTYPE), i32(phase), i32(self.n),
                 self._a.ctypes.data, self._ia.ctypes.data, self._ja.ctypes.data, self._perm.ctypes.data,
                 i32(nrhs), self._iparm.ctypes.data, i32(0), b.ctypes.data, x.ctypes.data, ctypes.byref(err))
        if err.value != 0:
            raise _PardisoError(f"PARDISO phase {phase} failed with error {err.value}")

    def same_pattern(self, U: sp.csr_matrix) -> bool:
        """Whether ``U`` (an upper triangle, sorted) has this factor's sparsity pattern."""
        return (self._open and U.shape[0] == self.n and np.array_equal(U.indptr, self._ia)
                and np.array_equal(U.indices, self._ja))

    def refactor(self, values: np.ndarray) -> None:
        """Factor the matrix of this pattern with other ``values`` (phase 22: the analysis kept)."""
        self._a = np.ascontiguousarray(values, dtype=self._dtype)
        self._call(22, np.zeros(1, self._dtype), np.zeros(1, self._dtype), 1)

    def solve(self, b: np.ndarray, overwrite_b: bool = False) -> np.ndarray:
        if not self._open:
            raise RuntimeError("the factor was closed")
        one = b.ndim == 1
        B = np.asfortranarray(b.reshape(self.n, -1), dtype=self._dtype)  # PARDISO wants column-major
        # in place where b itself is what PARDISO reads (iparm[5] = 1: the solution over b; x must
        # still be given, but reads back untouched). Bit for bit the same solution, without a
        # second array of b's size written: each fresh page costs the kernel its zeroing (and a
        # virtual machine's host its backing: about 2 s of CPU a GB on the 530k bench's machine)
        in_place = overwrite_b and np.shares_memory(B, b)
        X = np.zeros(B.shape, dtype=self._dtype, order="F")  # (calloc: pages are touched once, by PARDISO)
        self._iparm[5] = 1 if in_place else 0
        try:
            self._call(33, B, X, B.shape[1])
        finally:
            self._iparm[5] = 0
        out = B if in_place else X
        return out[:, 0] if one else out

    def close(self) -> None:
        if getattr(self, "_open", False):
            self._open = False
            self._call(-1, np.zeros(1, self._dtype), np.zeros(1, self._dtype), 1)  # release all of PARDISO's memory

    def __del__(self):
        try:
            self.close()
        except Exception:  # noqa: BLE001 - interpreter shutdown
            pass


_BACKENDS = {"pardiso": _Pardiso, "cholmod": _Cholmod, "superlu": _SuperLU}


def _upper_triangle(A: sp.csr_matrix) -> sp.csr_matrix:
    return sp.triu(A, format="csr")


def constrained_split(n_vertices: int, handles: np.ndarray, anchors: np.ndarray | None):
    """Indices of the free vertices and a boolean mask of the constrained ones."""
    constrained = np.zeros(n_vertices, dtype=bool)
    constrained[np.asarray(handles, dtype=np.int64)] = True
    if anchors is not None and len(anchors):
        constrained[np.asarray(anchors, dtype=np.int64)] = True
    return np.flatnonzero(~constrained), constrained


@dataclass(frozen=True)
class ShellBasis:
    """The large-scale basis B and the sparse solver that made it.

    B : (V, H) float64 (see :func:`shell_basis`).
    solver : the backend that factored the shell ("pardiso", "cholmod" or "superlu"); None
        where nothing was factored (every vertex prescribed).
    passed_over : backend -> why it was passed over before ``solver`` (a fallback is recorded).
    """

    B: np.ndarray
    solver: str | None
    passed_over: dict = field(default_factory=dict)


def shell_basis(vertices: np.ndarray, faces: np.ndarray, handles: np.ndarray, anchors: np.ndarray | None = None,
                k_stretch: float = 0.0, k_bend: float = 1.0, spacing: float | None = None,
                columns: np.ndarray | None = None) -> np.ndarray:
    """The large-scale basis B alone; see :func:`solve_shell_basis`."""
    return solve_shell_basis(vertices, faces, handles, anchors, k_stretch, k_bend, spacing, columns).B


def solve_shell_basis(vertices: np.ndarray, faces: np.ndarray, handles: np.ndarray,
                      anchors: np.ndarray | None = None, k_stretch: float = 0.0, k_bend: float = 1.0,
                      spacing: float | None = None, columns: np.ndarray | None = None) -> ShellBasis:
    """The large-scale basis B: displacements u = B · u_H for handle displacements u_H.

    Parameters
    ----------
    vertices : (V, 3) rest positions; faces : (T, 3) triangles.
    handles : (H,) int vertex indices whose displacement is prescribed.
    anchors : (A,) int vertex indices held at zero displacement, or None.
    k_stretch, k_bend : shell stiffnesses; k_stretch relative to the marker spacing.
    spacing : marker spacing h (length units); default: mean nearest-handle distance.
    columns : optional (A,) extra prescribed vertices to return columns for
        (normally the anchors, whose displacement is zero so their columns are unused).

    Returns
    -------
    :class:`ShellBasis` with B : (V, H) float64, column-major (or (V, H + len(columns))) — rows
        of handles are unit rows. Without anchors, every row sums to 1: a rigid translation is
        reproduced. And the solver that factored the system.
    """
    vertices = np.asarray(vertices, dtype=np.float64)
    handles = np.asarray(handles, dtype=np.int64)
    n = vertices.shape[0]
    if spacing is None:
        spacing = marker_spacing(vertices, handles)
    A = shell_operator(vertices, faces, k_stretch, k_bend, spacing)
    free, constrained = constrained_split(n, handles, anchors)
    driven = handles if columns is None else np.concatenate([handles, np.asarray(columns, dtype=np.int64)])
    U, R = constrained_system(A, constrained, driven)
    if not len(free):
        return ShellBasis(np.ascontiguousarray(R), None)
    factor = CholeskyFactor(U, upper=True)
    del U
    B = factor.solve(R, overwrite_b=True)  # R's columns become B's
    factor.close()
    del R
    # exactly the prescribed values on the constrained rows (the solve gives them up to round-off);
    # B stays column-major as the solver wrote it: a C-order copy would be 0.4 GB at 530k vertices,
    # and the products with B and the model file's float32 copy take either order
    B[constrained] = 0.0
    B[driven, np.arange(len(driven))] = 1.0
    return ShellBasis(B, factor.backend, dict(factor.passed_over))


def shell_displacements(vertices: np.ndarray, faces: np.ndarray, handles: np.ndarray, anchors: np.ndarray | None,
                        handle_displacements: np.ndarray, k_stretch: float = 0.0, k_bend: float = 1.0,
                        spacing: float | None = None, parts: "ShellParts | None" = None,
                        keep: dict | None = None) -> np.ndarray:
    """The shell's displacements u = B · u_H for a few handle displacements, without B.

    The same constrained system as :func:`solve_shell_basis`, solved for the given frames' 3·E
    right-hand sides instead of B's H columns: where only a few poses are needed (validating the
    stiffness on the examples) this is the factorisation plus a few substitutions.

    Parameters
    ----------
    handle_displacements : (E, H, 3) displacements of ``handles``; parts : the mesh's
        :class:`ShellParts`, if at hand; keep : a dict that keeps the factor (``"factor"``) for
        the next call with other stiffnesses on the same mesh and handles, which factors only
        the new values (the caller closes it); other parameters as in :func:`solve_shell_basis`.

    Returns
    -------
    (E, V, 3) float64 displacements: ``handle_displacements`` on the handles, 0 on the anchors.
    """
    vertices = np.asarray(vertices, dtype=np.float64)
    handles = np.asarray(handles, dtype=np.int64)
    u_h = np.asarray(handle_displacements, dtype=np.float64)
    n, E = vertices.shape[0], u_h.shape[0]
    if spacing is None:
        spacing = marker_spacing(vertices, handles)
    A = sp.csr_matrix(parts.operator(k_stretch, k_bend, spacing) if parts is not None
                      else shell_operator(vertices, faces, k_stretch, k_bend, spacing))
    free, constrained = constrained_split(n, handles, anchors)
    U, _ = constrained_system(A, constrained, handles[:0])
    x = np.zeros((n, 3 * E))
    x[handles] = np.moveaxis(u_h, 0, 1).reshape(len(handles), 3 * E)
    # the free rows move with −A_fh u_h; the prescribed rows hold their values (as B's columns do)
    rhs = -(A @ x)
    rhs[constrained] = 0.0
    rhs[handles] = x[handles]
    if not free.any():
        return np.moveaxis(rhs.reshape(n, E, 3), 1, 0).copy()
    factor = None if keep is None else keep.get("factor")
    if factor is None:
        factor = CholeskyFactor(U, upper=True)
    else:
        factor.refactor(U, upper=True)
    del U
    out = factor.solve(np.asfortranarray(rhs), overwrite_b=True)
    if keep is None:
        factor.close()
    else:
        keep["factor"] = factor
    out[constrained] = 0.0
    out[handles] = x[handles]
    return np.moveaxis(out.reshape(n, E, 3), 1, 0).copy()


def constrained_system(A: sp.spmatrix, constrained: np.ndarray, driven: np.ndarray
                       ) -> tuple[sp.csr_matrix, np.ndarray]:
    """The symmetric system A with its constrained rows and columns replaced by the identity.

    Returns its upper triangle U (what PARDISO reads), the right-hand sides R (n, D) in column
    order (−A[:, driven] on the free rows, the identity on the driven rows, zero on the other
    constrained rows). U X = R gives X[free] =
    −A_ff⁻¹ A_f,driven and X = R on the constrained rows: the basis B itself, without cutting
    the free block out of A (at 530k vertices a second copy of 12M non-zeros and a second
    pass to cut its triangle).

    Parameters
    ----------
    A : (n, n) symmetric sparse matrix; constrained : (n,) bool; driven : (D,) constrained
        vertex indices whose columns are returned.
    """
    A = sp.csr_matrix(A)
    n = A.shape[0]
    indptr, indices = A.indptr, A.indices
    rows = np.repeat(np.arange(n, dtype=indices.dtype), np.diff(indptr))
    free = ~constrained
    keep = indices > rows
    keep &= free[indices]
    keep &= free[rows]
    del rows
    # each row of U: its diagonal (A's on a free row, 1 on a constrained one), then the kept entries
    per_row = np.add.reduceat(keep, indptr[:-1]) if len(keep) else np.zeros(n, dtype=np.int64)
    per_row = np.where(np.diff(indptr) > 0, per_row, 0) + 1  # (reduceat repeats a value at an empty row)
    u_ptr = np.zeros(n + 1, dtype=np.int64)
    np.cumsum(per_row, out=u_ptr[1:])
    if u_ptr[-1] > np.iinfo(np.int32).max:
        raise ValueError("the shell system is too large for 32-bit sparse indices")
    is_diag = np.zeros(int(u_ptr[-1]), dtype=bool)
    is_diag[u_ptr[:-1]] = True
    u_indices = np.empty(is_diag.shape[0], dtype=np.int32)
    u_data = np.empty(is_diag.shape[0], dtype=np.float64)
    u_indices[is_diag] = np.arange(n, dtype=np.int32)
    u_data[is_diag] = np.where(constrained, 1.0, A.diagonal())
    u_indices[~is_diag] = indices[keep]
    u_data[~is_diag] = A.data[keep]
    U = sp.csr_matrix((u_data, u_indices, u_ptr.astype(np.int32)), shape=(n, n))
    # A's columns of the driven vertices are its rows (symmetric): a few thousand entries
    driven = np.asarray(driven, dtype=np.int64)
    rows_d = A[driven]
    # only the few rows the driven columns reach are written (zeroing the constrained rows
    # explicitly would touch pages all over a 0.4 GB array that calloc left untouched)
    R = np.zeros((n, len(driven)), order="F")
    for j in range(len(driven)):
        lo, hi = rows_d.indptr[j], rows_d.indptr[j + 1]
        rows = rows_d.indices[lo:hi]
        on_free = ~constrained[rows]
        R[rows[on_free], j] = -rows_d.data[lo:hi][on_free]
    R[driven, np.arange(len(driven))] = 1.0
    return U, R


def large_scale_positions(rest: np.ndarray, B: np.ndarray, handle_displacements: np.ndarray) -> np.ndarray:
    """Rest positions plus B · u_H, batched over frames.

    Parameters
    ----------
    rest : (V, 3); B : (V, H); handle_displacements : (..., H, 3).

    Returns
    -------
    (..., V, 3) positions, in the dtype of B.
    """
    u = np.einsum("vh,...hc->...vc", B, handle_displacements.astype(B.dtype, copy=False), optimize=True)
    return u + rest.astype(B.dtype, copy=False)
