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
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from facepipe.core.psd import edge_weight_matrix
from facepipe.core.strain import strain_features
from facepipe.core.tangent_frames import local_frames, to_world, vertex_face_matrix

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
        self.sub_incidence = vertex_face_matrix(self.sub_faces, len(used))
        self.alpha = alpha[patch]
        self.weights = model.rbf_weights[patch].astype(np.float32)
        self.const = model.rbf_const[patch].astype(np.float32)
        self.basis = model.basis_features.astype(np.float64)
        self.confidence = None if site is None else np.asarray(self.alpha @ site).ravel().astype(np.float32)

    def shift(self, offset) -> np.ndarray:
        """B[:, h] δ (V, 3) float32: the large scale's change everywhere (also the page's to add,
        :meth:`evaluate_patch` answers the rest)."""
        return self.column[:, None] * np.asarray(offset, dtype=np.float64).astype(np.float32)[None]

    def evaluate_patch(self, offset) -> np.ndarray:
        """Final positions (n, 3) float32 of the patch's vertices (:attr:`patch`) with the handle
        moved by ``offset``; outside the patch the final surface is ``base_final`` + :meth:`shift`."""
        offset = np.asarray(offset, dtype=np.float64)
        sub = self.base_large[self.used] + self.column[self.used, None] * offset.astype(np.float32)[None]
        if self.method == "none":
            return sub[self.patch_local]
        handles = self.base_handles.copy()
        handles[self.handle] += offset
        features = strain_features(handles, self.edges, self.rest_lengths)
        # float32 on the patch: this is what the pointer sees, the exact frame follows
        frames = local_frames(sub, self.sub_faces, self.sub_neighbours, self.sub_incidence)[self.patch_local]
        sq = (features[None, :] - self.basis) ** 2  # (P, F)
        if self.method == "wpsd":
            phi = np.sqrt(np.maximum(np.asarray(self.alpha @ sq.T), 0.0)).astype(np.float32)  # (n, P)
        else:
            phi = np.broadcast_to(np.sqrt(sq.sum(axis=1))[None], (len(self.patch), sq.shape[0])).astype(np.float32)
        d = np.einsum("vp,vpc->vc", phi, self.weights) + self.const
        if self.confidence is not None:
            d *= self.confidence[:, None]
        return (sub[self.patch_local] + to_world(frames, d)).astype(np.float32)

    def evaluate(self, offset) -> tuple[np.ndarray, np.ndarray]:
        """Final and large-scale positions (V, 3) float32 with the handle moved by ``offset`` from the base."""
        delta = self.shift(offset)
        large = self.base_large + delta
        final = self.base_final + delta
        final[self.patch] = self.evaluate_patch(offset)
        return final, large
