"""Server-side evaluation of a drag for meshes too large to re-evaluate whole at every move.

While one handle h is dragged at one frame, everything but its offset δ is fixed, and

* the large scale is linear in δ: large(δ) = large₀ + B[:, h] δᵀ — updated exactly, everywhere;
* the strain changes only on the feature edges at h, so the WPSD distances change only at the
  vertices whose edge weights α reach those edges;
* the local frames change wherever the large scale does, but they turn with its gradient, and
  B[:, h] decays away from h: where |B[v, h]| is below ``support`` (1 % of the handle's own
  motion) the frames turn by a negligible amount.

So a drag re-evaluates frames and details only on the *patch*: the vertices where
|B[v, h]| ≥ ``support`` or α reaches h's edges (frames of a patch vertex need all its incident
faces). Outside the patch the large scale is exact and the details keep their frame from the
drag's start. The editor evaluates the whole frame exactly once the drag stops (the gate's exact
fits arrive), so the patch only shapes what is seen while the pointer moves.

A step costs O(patch) elementwise arithmetic, no sparse products: with the large scale
p = a + c δ on the patch (a its base, c B's column), every face normal
(A₁ + C₁δ) × (A₂ + C₂δ) = A₁ × A₂ + (C₂A₁ − C₁A₂) × δ is linear in δ (the δ × δ term vanishes),
hence so is each vertex's area-weighted sum n₀ + n₁ × δ, and so is the edge to its frame
neighbour; the WPSD distances change only through the features of h's edges, so the rest of
α's product is formed once.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from facepipe.core.psd import edge_weight_matrix
from facepipe.core.strain import strain_features
from facepipe.core.tangent_frames import frames_from_normals, vertex_face_matrix

# B weights below this fraction of the handle's own motion leave a vertex's frame to the full
# evaluation (on the 530k sample face: a patch of 10 % of the vertices)
DEFAULT_SUPPORT = 1e-2


class DragPatch:
    """Incremental evaluation of one handle's drag from an exactly evaluated base frame.

    Parameters
    ----------
    model : the baked model; handle : the dragged handle's index.
    base_handles : (H, 3) handle positions without the drag's offset.
    base_final, base_large : (V, 3) the exact evaluation of ``base_handles``.
    site : (F,) the gate's per-site confidence used during the drag (None without a gate).
    """

    def __init__(self, model, handle: int, base_handles: np.ndarray, base_final: np.ndarray,
                 base_large: np.ndarray, site: np.ndarray | None, support: float = DEFAULT_SUPPORT,
                 incidence: sp.csr_matrix | None = None):
        self.model = model
        self.handle = handle
        self.base_handles = base_handles.astype(np.float64)
        self.base_final = base_final.astype(np.float32)
        self.base_large = base_large.astype(np.float32)
        self.column = model.B[:, handle].astype(np.float32)
        self.method = model.method
        self.site = site
        edges = model.edges.astype(np.int64)
        self.edges, self.rest_lengths = edges, model.rest_lengths.astype(np.float64)
        touched = np.flatnonzero((edges == handle).any(axis=1))
        alpha = edge_weight_matrix(model.edge_index, model.edge_weight, len(edges))
        reached = np.asarray(alpha[:, touched].sum(axis=1)).ravel() != 0 if len(touched) else np.zeros(len(self.column), bool)
        patch = np.flatnonzero((np.abs(self.column) >= support) | reached)
        self.patch = patch
        if incidence is None:
            incidence = vertex_face_matrix(model.triangles.astype(np.int64), model.n_vertices)
        faces = model.triangles[np.unique(incidence[patch].indices)].astype(np.int64)
        neighbours = model.frame_neighbors.astype(np.int64)[patch]
        # the sub-mesh: the patch's incident faces, over the vertices they and the frame neighbours use
        used = np.unique(np.concatenate([faces.ravel(), neighbours, patch]))
        local = np.full(model.n_vertices, -1, dtype=np.int64)
        local[used] = np.arange(len(used))
        self.used, self.sub_faces = used, local[faces]
        self.sub_neighbours = local[model.frame_neighbors.astype(np.int64)[used]]
        self.sub_neighbours[self.sub_neighbours < 0] = np.arange(len(used))[self.sub_neighbours < 0]  # (unused rows)
        self.patch_local = local[patch]
        self.alpha = alpha[patch]
        self.basis = model.basis_features.astype(np.float64)
        self.confidence = None if site is None else np.asarray(self.alpha @ site).ravel().astype(np.float32)
        # the large scale on the patch's sub-mesh, a + c δ, and what is linear in δ (module
        # docstring); formed in float64, kept by coordinate (3, n) in float32 for the steps
        a = self.base_large[used].astype(np.float64)
        c = self.column[used].astype(np.float64)
        f0, f1, f2 = (self.sub_faces[:, k] for k in range(3))
        A1, A2, C1, C2 = a[f1] - a[f0], a[f2] - a[f0], (c[f1] - c[f0])[:, None], (c[f2] - c[f0])[:, None]
        incidence_patch = vertex_face_matrix(self.sub_faces, len(used))[self.patch_local]
        neighbour = self.sub_neighbours[self.patch_local]
        soa = lambda x: np.ascontiguousarray(np.asarray(x, dtype=np.float32).T)  # noqa: E731
        self.normal0 = soa(incidence_patch @ np.cross(A1, A2))
        self.normal1 = soa(incidence_patch @ (C2 * A1 - C1 * A2))
        self.edge0, self.edge1 = soa(a[neighbour] - a[self.patch_local]), (c[neighbour] - c[self.patch_local]).astype(np.float32)
        self.point0, self.point1 = soa(a[self.patch_local]), c[self.patch_local].astype(np.float32)
        self.weights_soa = np.ascontiguousarray(model.rbf_weights[patch].astype(np.float32).transpose(1, 2, 0))  # (P, 3, n)
        self.const_soa = soa(model.rbf_const[patch])
        # the WPSD distances: α's columns of h's features change with δ, the rest stays at the base's
        self.touched = touched
        if self.method == "wpsd":
            base_sq = (strain_features(self.base_handles, edges, self.rest_lengths)[None, :] - self.basis) ** 2
            base_sq[:, touched] = 0.0
            self.fixed_sq = np.ascontiguousarray(np.asarray(self.alpha @ base_sq.T).T, dtype=np.float32)  # (P, n)
            self.alpha_touched = np.ascontiguousarray(self.alpha[:, touched].toarray().T, dtype=np.float32)  # (k, n)

    def shift(self, offset) -> np.ndarray:
        """B[:, h] δ (V, 3) float32: the large scale's change everywhere (also the page's to add,
        :meth:`evaluate_patch` answers the rest)."""
        return self.column[:, None] * np.asarray(offset, dtype=np.float64).astype(np.float32)[None]

    def frames(self, offset) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The patch's frames t, b, n, each (3, n) float32 (by coordinate), with the handle moved
        by ``offset``: n = normalise(n₀ + n₁ × δ), t = e − (e·n) n normalised, b = n × t —
        :func:`~facepipe.core.tangent_frames.local_frames`' arithmetic, its fallbacks included."""
        offset = np.asarray(offset, dtype=np.float64)
        dx, dy, dz = (np.float32(v) for v in offset)
        (px, py, pz), (qx, qy, qz) = self.normal0, self.normal1
        nx, ny, nz = px + (qy * dz - qz * dy), py + (qz * dx - qx * dz), pz + (qx * dy - qy * dx)
        ex, ey, ez = self.edge0[0] + self.edge1 * dx, self.edge0[1] + self.edge1 * dy, self.edge0[2] + self.edge1 * dz
        with np.errstate(invalid="ignore", divide="ignore"):  # degenerate rows are redone below
            n_len = np.sqrt(nx * nx + ny * ny + nz * nz)
            nx, ny, nz = nx / n_len, ny / n_len, nz / n_len
            en = ex * nx + ey * ny + ez * nz
            tx, ty, tz = ex - en * nx, ey - en * ny, ez - en * nz
            t_len = np.sqrt(tx * tx + ty * ty + tz * tz)
            tx, ty, tz = tx / t_len, ty / t_len, tz / t_len
        bx, by, bz = ny * tz - nz * ty, nz * tx - nx * tz, nx * ty - ny * tx
        # a degenerate normal or tangent (rare) takes local_frames' fallbacks, by the shared code
        odd = ~((n_len > 1e-30) & (t_len > 1e-6 * np.sqrt(ex * ex + ey * ey + ez * ez)))
        if odd.any():
            normal = self.normal0[:, odd].T + np.cross(self.normal1[:, odd].T, offset)
            length = np.linalg.norm(normal, axis=1, keepdims=True)
            normal = np.where(length > 1e-30, normal / np.where(length > 1e-30, length, 1.0), [0.0, 0.0, 1.0])
            R = frames_from_normals(normal, np.stack([ex[odd], ey[odd], ez[odd]], 1)).T  # (column, coordinate, m)
            (tx[odd], ty[odd], tz[odd]), (bx[odd], by[odd], bz[odd]), (nx[odd], ny[odd], nz[odd]) = R
        return np.stack([tx, ty, tz]), np.stack([bx, by, bz]), np.stack([nx, ny, nz])

    def evaluate_patch(self, offset) -> np.ndarray:
        """Final positions (n, 3) float32 of the patch's vertices (:attr:`patch`) with the handle
        moved by ``offset``; outside the patch the final surface is ``base_final`` + :meth:`shift`."""
        offset = np.asarray(offset, dtype=np.float64)
        dx, dy, dz = (np.float32(v) for v in offset)
        large = self.point0 + self.point1 * np.array([dx, dy, dz])[:, None]  # (3, n)
        if self.method == "none":
            return np.ascontiguousarray(large.T)
        handles = self.base_handles.copy()
        handles[self.handle] += offset
        features = strain_features(handles, self.edges, self.rest_lengths)
        (tx, ty, tz), (bx, by, bz), (nx, ny, nz) = self.frames(offset)
        if self.method == "wpsd":
            sq = ((features[None, self.touched] - self.basis[:, self.touched]) ** 2).astype(np.float32)  # (P, k)
            phi = np.sqrt(np.maximum(self.fixed_sq + sq @ self.alpha_touched, 0.0))  # (P, n)
        else:
            sq = (features[None, :] - self.basis) ** 2  # (P, F)
            phi = np.sqrt(sq.sum(axis=1)).astype(np.float32)[:, None]
        d = self.const_soa.copy()  # (3, n): the details in the frame
        for p in range(len(phi)):
            d += phi[p] * self.weights_soa[p]
        if self.confidence is not None:
            d *= self.confidence
        out = np.empty((len(self.patch), 3), dtype=np.float32)
        out[:, 0] = large[0] + tx * d[0] + bx * d[1] + nx * d[2]
        out[:, 1] = large[1] + ty * d[0] + by * d[1] + ny * d[2]
        out[:, 2] = large[2] + tz * d[0] + bz * d[1] + nz * d[2]
        return out

    def evaluate(self, offset) -> tuple[np.ndarray, np.ndarray]:
        """Final and large-scale positions (V, 3) float32 with the handle moved by ``offset`` from the base."""
        delta = self.shift(offset)
        large = self.base_large + delta
        final = self.base_final + delta
        final[self.patch] = self.evaluate_patch(offset)
        return final, large
