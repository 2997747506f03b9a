"""Non-rigid registration of a surface onto another: closest points regularised by the thin shell.

After a fit to a few marked points, a source surface lies on the target only near the points;
between and beyond them (neck, ears, back of the head) it can be centimetres off. The surface is
then refined by non-rigid ICP (in the spirit of Amberg et al. 2007, "Optimal step nonrigid ICP"):
every source vertex is paired with the closest point of the target whose normal agrees with its
own (not on the target's border, where a closest point only means the target ends), and the
source takes the step u that minimises

    λ uᵀ A u + Σ_v m_v w_v |x_v + u_v − c_v|²,     u = 0 at the marked points,

A = K M⁻¹ K the shell's bending operator (:func:`facepipe.core.shell.shell_operator`), m the
vertex areas, w = 1 for a pair and 0 for none. λ = ℓ⁴ in length units: ℓ is the length below
which the displacement cannot bend, so the pairs are re-found and the system solved again for
ℓ halving from the points' spacing down to the mesh's edge length (coarse alignment first, detail
last; the pairs of a stiff step are reliable enough to guide the next, softer one).

Pure arrays; one sparse factorisation per solve.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from facepipe.core.closest import project_points
from facepipe.core.mesh import unique_edges
from facepipe.core.shell import CholeskyFactor, massmatrix, shell_operator
from facepipe.core.tangent_frames import vertex_normals

__all__ = ["Refinement", "border_vertices", "refine_to_surface"]

# a pair is dropped when its closest point lies on the target's border (weight of the border
# corners of its triangle above this): the surfaces end in different places, there is nothing to match
ON_BORDER = 1.0 - 1e-6


@dataclass
class Refinement:
    """What :func:`refine_to_surface` returns.

    vertices : (V, 3) the refined source; lengths : the ℓ of each stiffness step;
    paired : (V,) bool, the vertices paired with the target in the last solve;
    distance : (V,) from each refined vertex to the target surface.
    """

    vertices: np.ndarray
    lengths: list[float]
    paired: np.ndarray
    distance: np.ndarray


def border_vertices(faces: np.ndarray, n_vertices: int) -> np.ndarray:
    """(V,) bool: vertices on an edge used by one triangle only."""
    f = np.asarray(faces, dtype=np.int64)
    e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    _, inverse, counts = np.unique(e, axis=0, return_inverse=True, return_counts=True)
    single = e[counts[inverse.ravel()] == 1]
    out = np.zeros(n_vertices, dtype=bool)
    out[single.ravel()] = True
    return out


def stiffness_lengths(spacing: float, edge: float, steps: int | None = None) -> list[float]:
    """ℓ halving from the points' ``spacing`` down to the mean ``edge`` length (at least one step)."""
    lengths = [float(spacing)]
    while lengths[-1] / 2 >= edge and (steps is None or len(lengths) < steps):
        lengths.append(lengths[-1] / 2)
    return lengths


def refine_to_surface(vertices: np.ndarray, faces: np.ndarray, target_vertices: np.ndarray,
                      target_faces: np.ndarray, fixed: np.ndarray, spacing: float, iterations: int = 5,
                      min_cos: float = 0.5, max_distance: float | None = None) -> Refinement:
    """Move a surface onto a target, holding ``fixed`` vertices where they are (see the module docstring).

    Parameters
    ----------
    vertices : (V, 3), faces : (F, 3) the source, already fitted to the marked points.
    target_vertices : (Vt, 3), target_faces : (Ft, 3).
    fixed : (N,) int source vertices that stay put (the marked points, on the target already).
    spacing : the points' spacing: the first, stiffest step's ℓ.
    iterations : pairings and solves per stiffness.
    min_cos : a pair's normals must agree within acos(min_cos).
    max_distance : pairs farther apart are dropped (default 2 × ``spacing``: the fit to the points
        leaves the surfaces closer than that wherever they are the same kind of surface).
    """
    X0 = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    Y = np.asarray(target_vertices, dtype=np.float64)
    G = np.asarray(target_faces, dtype=np.int64)
    V = len(X0)
    limit = 2.0 * spacing if max_distance is None else float(max_distance)
    e = unique_edges(faces)
    edge = float(np.linalg.norm(X0[e[:, 0]] - X0[e[:, 1]], axis=1).mean())
    lengths = stiffness_lengths(spacing, edge)
    A = shell_operator(X0, faces, k_stretch=0.0, k_bend=1.0).tocsr()
    mass = massmatrix(X0, faces)
    free = np.ones(V, dtype=bool)
    free[np.asarray(fixed, dtype=np.int64)] = False
    fi = np.flatnonzero(free)
    A_ff = A[fi][:, fi]
    target_border = border_vertices(G, len(Y))
    Yn = vertex_normals(Y, G)
    X = X0.copy()
    paired = np.zeros(V, dtype=bool)
    factor = None  # every step's matrix has A_ff's pattern: factored again numerically, the analysis kept
    for ell in lengths:
        for _ in range(iterations):
            c, paired = _pairs(X, faces, Y, G, Yn, target_border, min_cos, limit)
            # each solve is a step from where the last left the surface, smooth at the scale ℓ (the
            # steps add up, so a stiff step does not hold back the fit of the softer ones); a vertex
            # without a pair keeps a tiny pull to stay where it is, so that a part of the mesh with
            # neither pairs nor points is not singular
            w = np.where(paired, 1.0, 1e-6) * mass
            goal = np.where(paired[:, None], c - X, 0.0)
            M = (ell ** 4) * A_ff + sp.diags(w[fi])
            if factor is None:
                factor = CholeskyFactor(M.tocsr())
            else:
                factor.refactor(M)
            u = np.zeros_like(X0)
            u[fi] = factor.solve(w[fi, None] * goal[fi])
            X = X + u
    if factor is not None:
        factor.close()
    _, _, distance, _ = project_points(X, vertex_normals(X, faces), Y, G, min_cos=-1.0)
    return Refinement(X, lengths, paired, distance)


def _pairs(X, faces, Y, G, Yn, target_border, min_cos: float, limit: float):
    """The closest target point of each source vertex, and whether it makes a pair: normals that
    agree, not on the target's border, nearer than ``limit``."""
    Xn = vertex_normals(X, faces)
    face, bary, dist, ok = project_points(X, Xn, Y, G, min_cos=min_cos)
    corners = G[face]
    c = np.einsum("vk,vkx->vx", bary, Y[corners])
    on_border = (bary * target_border[corners]).sum(axis=1) > ON_BORDER
    # the target's surface normal at the closest point must agree too (the face's own test is
    # per triangle; a vertex normal blends the triangles around, so a fold's other side is refused)
    n_at = np.einsum("vk,vkx->vx", bary, Yn[corners])
    agree = np.einsum("vx,vx->v", Xn, n_at) >= min_cos * np.linalg.norm(n_at, axis=1)
    return c, ok & agree & ~on_border & (dist <= limit)
