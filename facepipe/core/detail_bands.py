"""Spatial frequency bands of a displacement field on a mesh, and how much of each a surface already carries.

A rig's own surface (a point cache) already has part of what the details of a mocap model
correct the thin shell for — mostly the smooth part between the markers — and, for a rig with
wrinkles, possibly all of it. Which part is measured on the cache itself: its deviation from the
shell's smooth solution for the same handles, e = cache − shell, is regressed on the frequency
bands of the model's details D = Σ_b D_b,

    e ≈ Σ_b α_b D_b,   0 ≤ α_b ≤ 1   (bounded least squares over all vertices and frames),

and (1 − α_b) of every band is added. A band the cache already has (α ≈ 1) is not added twice; a
band it lacks (α ≈ 0) is added whole. Deviations of the cache unrelated to the details (the rig's
own shapes) are uncorrelated with D and leave the α's alone.

The bands come from screened-Poisson low-passes L_ℓ D = (M + ℓ² K)⁻¹ M D (K the cotangent
stiffness, M the lumped mass): a heat-kernel-like smoothing over the length ℓ, the same on any mesh
resolution, so the bands are set by lengths (multiples of the marker spacing), not by vertex counts.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.optimize import lsq_linear

from facepipe.core.shell import CholeskyFactor, cotmatrix, massmatrix

#: Cut-off wavelengths of the band edges in marker spacings: details finer than half the
#: spacing (wrinkles), up to one, two and four spacings (what the shell misses between markers),
#: and coarser.
BAND_WAVELENGTHS = (0.5, 1.0, 2.0, 4.0)


class DetailBands:
    """Band decomposition of (C, V, 3) displacement fields on one mesh.

    Parameters
    ----------
    vertices : (V, 3) the rest mesh; faces : (T, 3).
    spacing : the marker spacing (length units); the band edges are ``BAND_WAVELENGTHS`` × spacing.

    Attributes
    ----------
    wavelengths : (K,) band edges, finest first; there are K + 1 bands, band 0 the finest.
    """

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, spacing: float,
                 wavelengths: tuple = BAND_WAVELENGTHS):
        self.wavelengths = np.asarray(wavelengths, dtype=np.float64) * float(spacing)
        self._K = cotmatrix(vertices, faces)
        self._mass = massmatrix(vertices, faces)
        self._factors: dict[int, CholeskyFactor] = {}

    @property
    def n_bands(self) -> int:
        return len(self.wavelengths) + 1

    def lowpass(self, level: int, D: np.ndarray) -> np.ndarray:
        """L_level D: the field smoothed below wavelength ``wavelengths[level]`` ((C, V, 3) or (V, 3))."""
        if level not in self._factors:
            ell = self.wavelengths[level] / (2.0 * np.pi)  # a wave of wavelength λ is halved where λ = 2πℓ
            self._factors[level] = CholeskyFactor(sp.diags(self._mass) + ell**2 * self._K)
        D = np.asarray(D, dtype=np.float64)
        flat = np.moveaxis(D, -2, 0).reshape(D.shape[-2], -1)  # (V, C·3): all frames in one solve
        x = self._factors[level].solve(self._mass[:, None] * flat)
        return np.moveaxis(x.reshape((D.shape[-2],) + D.shape[:-2] + (3,)), 0, -2)

    def split(self, D: np.ndarray) -> list[np.ndarray]:
        """The K + 1 bands of ``D`` (finest first); they sum to ``D``."""
        lows = [np.asarray(D, dtype=np.float64)] + [self.lowpass(k, D) for k in range(len(self.wavelengths))]
        return [lows[k] - lows[k + 1] for k in range(len(self.wavelengths))] + [lows[-1]]

    def combine(self, D: np.ndarray, weights: np.ndarray, atol: float = 1e-6) -> np.ndarray:
        """Σ_b weights[b] · D_b without splitting where neighbouring weights agree.

        Σ_b c_b D_b = c_0 D + Σ_{k≥1} (c_k − c_{k−1}) L_{k−1} D (telescoping the bands), so only the
        low-passes at which the weight changes are solved: none when all weights are equal.
        """
        c = np.asarray(weights, dtype=np.float64)
        out = c[0] * np.asarray(D, dtype=np.float64)
        for k in range(1, len(c)):
            step = c[k] - c[k - 1]
            if abs(step) > atol:
                out = out + step * self.lowpass(k - 1, D)
        return out

    def close(self) -> None:
        for f in self._factors.values():
            f.close()
        self._factors.clear()


def band_gram(bands: list[np.ndarray], residual: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """G = ⟨D_i, D_j⟩ and g = ⟨D_i, e⟩ over every vertex and frame (sums to accumulate over chunks)."""
    flat = np.stack([np.asarray(b, dtype=np.float64).ravel() for b in bands])
    return flat @ flat.T, flat @ np.asarray(residual, dtype=np.float64).ravel()


def carried_fractions(G: np.ndarray, g: np.ndarray) -> np.ndarray:
    """α in [0, 1]^B minimising |Σ α_b D_b − e|² from the Gram sums of :func:`band_gram`.

    A band with no energy (all zero) gets α = 0 (nothing to add either way). The Gram matrix is
    regularised by a millionth of its trace so nearly collinear bands stay solvable.
    """
    G = np.asarray(G, dtype=np.float64)
    g = np.asarray(g, dtype=np.float64)
    n = len(g)
    live = np.diag(G) > 1e-12 * max(float(np.trace(G)), 1e-300)
    alpha = np.zeros(n)
    if not live.any():
        return alpha
    Gl = G[np.ix_(live, live)] + 1e-6 * np.trace(G) / n * np.eye(int(live.sum()))
    R = np.linalg.cholesky(Gl).T  # Gl = Rᵀ R: |R α − R⁻ᵀ g|² = αᵀ Gl α − 2 gᵀ α + const
    rhs = np.linalg.solve(R.T, g[live])
    alpha[live] = lsq_linear(R, rhs, bounds=(0.0, 1.0), method="bvls").x
    return alpha
