"""Fine-scale details as a function of the local strain of the large-scale surface, per vertex.

A wrinkle appears where the skin is compressed past a threshold, across the direction of the
compression: a nonlinear function of the *local* state of the skin, whatever expression put it
there. This model learns, at every vertex v, the detail d_v (3-vector in v's local frame) as a
function of the local strain s_v (:func:`facepipe.core.local_strain.vertex_strain`, 3 numbers,
rigid-invariant) of the large-scale surface, from the training poses (the examples, and the
frames of a captured performance where given):

    d_v(s) = Σ_i w_{v,i} k(|s − s_{v,i}|),      k(r) = exp(−r² / (2 σ²))

a Gaussian kernel ridge regression over the training poses' strains s_{v,i} at that vertex
(the rest pose, zero strain and zero detail, among them). A Gaussian kernel represents a
threshold (no detail below some compression, growing past it) and, because it decays, gives
**no detail where the current strain is farther than a few σ from every training pose's strain
at that vertex**: an expression unlike anything seen there gets the large scale alone. Strain has
no unit, so σ (``width``) is the same for any face at any scale. Because the function depends on
the vertex's own state only, a wrinkle learned from one expression appears in any other that
compresses the same skin the same way.

The per-vertex systems (K_v + λ I) w_v = D_v are independent (N × N, N training poses).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from facepipe.parallel import map_blocks

DEFAULT_WIDTH = 0.03
DEFAULT_RIDGE = 1e-3


@dataclass
class StrainDetailModel:
    """A fitted local-strain detail model.

    samples : (V, N, 3) the training poses' local strain at every vertex (the rest pose first).
    weights : (V, N, 3) kernel weights (local-frame units).
    width : σ, the kernel's width in strain units.
    ridge : λ the weights were fitted with (the training details are (K_v + λ I) w_v, which a
        replay that filters them needs; models saved before it was stored read the default).
    """

    samples: np.ndarray
    weights: np.ndarray
    width: float
    ridge: float = DEFAULT_RIDGE

    method = "local_strain"

    def evaluate(self, strain: np.ndarray, chunk: int = 8192) -> np.ndarray:
        """Details (Q, V, 3) in local frames for per-vertex strains (Q, V, 3)."""
        strain = np.asarray(strain, dtype=np.float64)
        Q, V = strain.shape[:2]
        out = np.empty((Q, V, 3))
        inv = -0.5 / self.width ** 2

        def block(start):
            stop = min(V, start + chunk)
            k = kernel_values(strain[:, start:stop], self.samples[start:stop], inv)  # (Q, n, N)
            out[:, start:stop] = np.einsum("qvn,vnc->qvc", k, self.weights[start:stop])

        map_blocks(block, range(0, V, chunk))
        return out

    def training_details(self, chunk: int = 1024) -> np.ndarray:
        """The details (N, V, 3) the model was fitted to, in the training poses' local frames:
        (K_v + λ I) w_v at every vertex (exact: the weights solve that system)."""
        V = self.samples.shape[0]
        out = np.empty(self.weights.shape)
        inv = -0.5 / self.width ** 2

        def block(start):
            stop = min(V, start + chunk)
            out[start:stop] = ridge_kernel(self.samples[start:stop], inv, self.ridge) @ self.weights[start:stop]

        map_blocks(block, range(0, V, chunk))
        return np.moveaxis(out, 1, 0)


def kernel_values(strain: np.ndarray, samples: np.ndarray, inv: float) -> np.ndarray:
    """exp(inv · |s_q,v − s_v,i|²): strains (Q, n, 3), samples (n, N, 3) → (Q, n, N)."""
    d2 = squared_distances(np.moveaxis(strain, 0, 1), samples)  # (n, Q, N)
    return np.exp(inv * np.moveaxis(d2, 1, 0))


def ridge_kernel(samples: np.ndarray, inv: float, ridge: float) -> np.ndarray:
    """K_v + λ I of every vertex's training strains (n, N, 3) → (n, N, N): the fit's system matrix."""
    return np.exp(inv * squared_distances(samples, samples)) + np.eye(samples.shape[1]) * ridge


def squared_distances(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """|a_vi − b_vj|² for per-vertex point sets a (n, I, 3), b (n, J, 3) → (n, I, J), never negative."""
    d2 = np.einsum("vic,vic->vi", a, a)[:, :, None] + np.einsum("vjc,vjc->vj", b, b)[:, None, :]
    d2 -= 2.0 * (a @ np.swapaxes(b, 1, 2))
    return np.maximum(d2, 0.0, out=d2)


def fit_strain_details(strains: np.ndarray, details: np.ndarray, width: float = DEFAULT_WIDTH,
                       ridge: float = DEFAULT_RIDGE, chunk: int = 1024) -> StrainDetailModel:
    """Fit the per-vertex kernel ridge regressions.

    Parameters
    ----------
    strains : (N, V, 3) local strain of the training poses' large-scale surfaces (pose 0: rest).
    details : (N, V, 3) their details in the large-scale surfaces' local frames.
    width : σ (strain units); ridge : λ added to the kernel matrix's diagonal (its diagonal is 1),
        which trades the training poses' exact reproduction for smoothness between them.

    Returns
    -------
    :class:`StrainDetailModel` (float64).
    """
    if width <= 0 or ridge < 0:
        raise ValueError("the kernel width must be > 0 and the ridge ≥ 0")
    samples = np.ascontiguousarray(np.moveaxis(np.asarray(strains, dtype=np.float64), 0, 1))  # (V, N, 3)
    targets = np.moveaxis(np.asarray(details, dtype=np.float64), 0, 1)  # (V, N, 3)
    V, N = samples.shape[:2]
    weights = np.empty((V, N, 3))
    inv = -0.5 / width ** 2

    def block(start):
        stop = min(V, start + chunk)
        K = ridge_kernel(samples[start:stop], inv, ridge)
        # K + λI is symmetric positive definite for λ > 0 (the Gaussian kernel is positive
        # semi-definite): a batched Cholesky-free solve is stable; the pseudo-inverse covers λ = 0
        if ridge > 0:
            weights[start:stop] = np.linalg.solve(K, targets[start:stop])
        else:
            weights[start:stop] = np.linalg.pinv(K, rcond=1e-10, hermitian=True) @ targets[start:stop]

    map_blocks(block, range(0, V, chunk))
    return StrainDetailModel(samples, weights, float(width), float(ridge))
