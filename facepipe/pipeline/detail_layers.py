"""The model's layers of a replay, evaluated again from its head-space handles.

A replay stores final positions; map exports need the fine-scale layer on its own. With the
clean head-space handles (``handles.npz``) any layer is cheap to evaluate again:

* ``local``: the details in the model's local frames (t, b, n) of the large-scale surface,
  d(f) = Σ_i w_i φ_i(f) + c. They depend only on the strain features of the handles, so no
  shell or frames are needed;
* ``tangent``: the same displacement in UV-aligned tangent frames of the large-scale
  surface (t along +u, b along +v, n the vertex normal; one frame per UV corner, so seams
  get their own): the convention of tangent-space vector displacement in renderers.
  The model's own frames take their tangent from a fixed neighbour of each vertex, which
  turns by tens of degrees from one vertex to the next, so their t and b coordinates cannot
  be interpolated across a triangle; UV-aligned frames vary smoothly;
* ``object``: the same displacement as a vector in the replay's output space,
  final − large (head motion applied when the replay kept it): what a renderer adds to the
  large-scale mesh in object-space vector displacement.

``local`` and ``object`` give one value per vertex, ``tangent`` one per UV index
(:attr:`DetailLayer.slots`).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from facepipe.errors import InputError
from facepipe.core.strain import strain_features
from facepipe.core.tangent_frames import local_frames, to_local, vertex_normals
from facepipe.pipeline.replay import NumpyEvaluator

SPACES = ("local", "tangent", "object")


def require_details(model) -> None:
    """InputError for a model without fine-scale details (method "none")."""
    if model.method == "none":
        raise InputError("the model has no fine-scale details (method 'none'): its displacement maps are zero",
                         path=model.path or None,
                         hint="bake the rig with [psd] method = 'wpsd' or 'psd' to export detail maps")


class DetailLayer:
    """Fine-scale displacements of frames of head-space handles.

    Parameters
    ----------
    model : facepipe.io.model_file.Model (method psd or wpsd).
    space : "local" (model frames t, b, n), "tangent" (UV-aligned frames) or "object"
        (output-space vectors).
    mesh : the rest mesh with UVs (facepipe.core.mesh.Mesh), needed for "tangent".

    Raises
    ------
    InputError
        A model without details (method "none").

    Example
    -------
    >>> layer = DetailLayer(model)                     # doctest: +SKIP
    >>> d = layer(handles["head"][:8])                 # (8, V, 3) local-frame details
    """

    def __init__(self, model, space: str = "local", mesh=None):
        require_details(model)
        if space not in SPACES:
            raise ValueError(f"unknown space {space!r}")
        if space == "tangent" and (mesh is None or mesh.uvs is None):
            raise InputError("tangent-space maps need the rest mesh's UVs", path=model.path or None,
                             hint="use --space local or object, or bake a rig whose mesh has UVs")
        self.model = model
        self.space = space
        self.mesh = mesh
        self.details = model.detail_model(np.float64)
        self.edges = model.edges.astype(np.int64)
        self.rest_lengths = model.rest_lengths.astype(np.float64)
        self.rest_handles = model.rest[model.handle_vertices].astype(np.float64)  # the gate's motion part
        self._evaluator = None

    @property
    def slots(self) -> str:
        """What the values are per: "vertex" or "uv" (UV index, for tangent space)."""
        return "uv" if self.space == "tangent" else "vertex"

    def features(self, head: np.ndarray) -> np.ndarray:
        """Strain features (C, F) of head-space handles (C, H, 3)."""
        return strain_features(np.asarray(head, dtype=np.float64), self.edges, self.rest_lengths)

    def __call__(self, head: np.ndarray, rotation: np.ndarray | None = None) -> np.ndarray:
        """Displacements (C, S, 3) float64 for head-space handles (C, H, 3); S = V, or the
        number of UVs for ``tangent``.

        ``rotation`` (C, 3, 3), the head motion to apply to ``object`` vectors (None: head space).
        """
        head = np.asarray(head, dtype=np.float64)
        if self.space == "local" and self.model.method != "local_strain":
            return self.details.evaluate(self.features(head), head - self.rest_handles)
        if self._evaluator is None:

            self._evaluator = NumpyEvaluator(self.model)
        final, large = self._evaluator.evaluate(head, with_large=True)
        d = final - large
        if self.space == "local":  # (local strain: its details, back in the large scale's frames)
            ev = self._evaluator
            return to_local(local_frames(large, ev.faces, ev.neighbors, ev.incidence), d)
        if self.space == "tangent":
            frames = uv_tangent_frames(large, self._evaluator.faces, self.mesh.face_uvs, self.mesh.uvs)
            return np.einsum("cuji,cuj->cui", frames, d[:, self.uv_vertex])
        if rotation is not None:
            d = np.einsum("cij,cvj->cvi", np.asarray(rotation, dtype=np.float64), d)
        return d

    @property
    def uv_vertex(self) -> np.ndarray:
        """(U,) the vertex of every UV index (the first corner that uses it)."""
        if getattr(self, "_uv_vertex", None) is None:
            uv_vertex = np.zeros(len(self.mesh.uvs), dtype=np.int64)
            uv_vertex[self.mesh.face_uvs.ravel()[::-1]] = self.mesh.faces.ravel()[::-1]
            self._uv_vertex = uv_vertex
        return self._uv_vertex


def uv_tangent_frames(vertices: np.ndarray, faces: np.ndarray, face_uvs: np.ndarray, uvs: np.ndarray) -> np.ndarray:
    """Orthonormal UV-aligned frames [t, b, n] per UV index, batched over frames.

    Per triangle the surface gradient of u (dP/du from the corner positions and UVs) is
    accumulated, weighted by the triangle's area, on the UV indices of its corners (UV indices
    with the same coordinates on the same vertex count as one, so they share a frame); t is
    that direction made perpendicular to the vertex normal n (area-weighted face normals,
    as :func:`facepipe.core.tangent_frames.vertex_normals`), and b = ±n × t with the sign of dP/dv, so a
    mirrored UV island gets a left-handed frame, as renderers expect.

    Parameters
    ----------
    vertices : (C, V, 3) positions; faces : (T, 3) vertex triangles; face_uvs : (T, 3) their
        UV indices; uvs : (U, 2).

    Returns
    -------
    (C, U, 3, 3) with [..., :, 0] = t, [..., :, 1] = b, [..., :, 2] = n (matrix columns, like
    :func:`facepipe.core.tangent_frames.local_frames`); components of a vector d are ``frames^T d``.
    """

    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    face_uvs = np.asarray(face_uvs, dtype=np.int64)
    U = len(uvs)
    uv = np.asarray(uvs, dtype=np.float64)[face_uvs]  # (T, 3, 2)
    du1, dv1 = uv[:, 1, 0] - uv[:, 0, 0], uv[:, 1, 1] - uv[:, 0, 1]
    du2, dv2 = uv[:, 2, 0] - uv[:, 0, 0], uv[:, 2, 1] - uv[:, 0, 1]
    det = du1 * dv2 - du2 * dv1
    inv = np.where(np.abs(det) > 1e-20, 1.0 / np.where(det == 0, 1.0, det), 0.0)
    p0 = vertices[:, faces[:, 0]]
    e1 = vertices[:, faces[:, 1]] - p0
    e2 = vertices[:, faces[:, 2]] - p0
    # [e1 e2] = [dP/du dP/dv] [[du1 du2], [dv1 dv2]]  →  invert the 2 × 2 UV matrix
    dpdu = (e1 * dv2[:, None] - e2 * dv1[:, None]) * inv[:, None]
    dpdv = (e2 * du1[:, None] - e1 * du2[:, None]) * inv[:, None]
    area = 0.5 * np.linalg.norm(np.cross(e1, e2), axis=-1, keepdims=True)
    dpdu = dpdu / np.maximum(np.linalg.norm(dpdu, axis=-1, keepdims=True), 1e-30) * area
    dpdv = dpdv / np.maximum(np.linalg.norm(dpdv, axis=-1, keepdims=True), 1e-30) * area
    C, T = vertices.shape[0], faces.shape[0]
    uv_vertex = np.zeros(U, dtype=np.int64)
    uv_vertex[face_uvs.ravel()[::-1]] = faces.ravel()[::-1]
    # UV indices naming the same point of the layout on the same vertex (duplicated 'vt' lines, not a
    # seam) are one corner with one frame, as tangent generators weld them (MikkTSpace): otherwise
    # each would see only its own triangles, and the maps two frames at one texel position
    _, group = np.unique(np.c_[uv_vertex, np.asarray(uvs, dtype=np.float64)], axis=0, return_inverse=True)
    group = group.ravel()
    G = int(group.max()) + 1 if U else 0
    # summing the triangles' vectors onto their UV corners, all frames at once: (G, T) @ (T, C·3)
    incidence = sp.csr_matrix((np.ones(3 * T), (group[face_uvs.ravel()], np.repeat(np.arange(T), 3))), shape=(G, T))

    def gather(x):
        acc = np.asarray(incidence @ np.moveaxis(x, 1, 0).reshape(T, -1)).reshape(G, C, 3)[group]
        return np.moveaxis(acc, 1, 0)

    T_acc, B_acc = gather(dpdu), gather(dpdv)
    n = vertex_normals(vertices, faces)[:, uv_vertex]
    t = T_acc - np.einsum("cui,cui->cu", T_acc, n)[..., None] * n
    tlen = np.linalg.norm(t, axis=-1, keepdims=True)
    # a UV corner without a usable u direction (degenerate UVs) falls back to any tangent
    alt = np.cross(n, np.array([1.0, 0.0, 0.0]))
    alt = np.where(np.linalg.norm(alt, axis=-1, keepdims=True) < 1e-6, np.cross(n, np.array([0.0, 1.0, 0.0])), alt)
    t = np.where(tlen > 1e-12, t / np.maximum(tlen, 1e-30), alt / np.maximum(np.linalg.norm(alt, axis=-1,
                                                                                             keepdims=True), 1e-30))
    b = np.cross(n, t)
    sign = np.where(np.einsum("cui,cui->cu", b, B_acc) < 0, -1.0, 1.0)
    return np.stack([t, sign[..., None] * b, n], axis=-1)


class StoredDetailLayer:
    """The detail layer of a replay whose large scale is stored, not evaluated (a mesh cache replayed
    as a take): final − large from ``positions.npy`` and ``large_scale.npy``, in the same spaces as
    :class:`DetailLayer` — ``local`` in the model's frames of the stored large-scale surface,
    ``tangent`` in its UV-aligned frames, ``object`` as vectors in the replay's space.
    """

    def __init__(self, replay, model, space: str = "local", mesh=None):
        if space not in SPACES:
            raise ValueError(f"unknown space {space!r}")
        if space == "tangent" and (mesh is None or mesh.uvs is None):
            raise InputError("tangent-space maps need the rest mesh's UVs", path=model.path or None,
                             hint="use --space local or object, or bake a rig whose mesh has UVs")
        self.replay, self.model, self.space, self.mesh = replay, model, space, mesh
        self.faces = model.triangles.astype(np.int64)
        self.neighbors = model.frame_neighbors.astype(np.int64)
        self._uv_vertex = None

    def __call__(self, s: int, e: int) -> np.ndarray:
        """Displacements (e − s, S, 3) of frames s..e−1."""
        large = np.asarray(self.replay.layer("large")[s:e], dtype=np.float64)
        d = np.asarray(self.replay.positions[s:e], dtype=np.float64) - large
        if self.space == "object":
            return d
        if self.space == "local":
            return to_local(local_frames(large, self.faces, self.neighbors), d)
        frames = uv_tangent_frames(large, self.faces, self.mesh.face_uvs, self.mesh.uvs)
        return np.einsum("cuji,cuj->cui", frames, d[:, DetailLayer.uv_vertex.fget(self)])
