"""Spatial frequency bands of a displacement field on a mesh, and how much of each a surface already carries.

A rig's own surface (a point cache) already has part of what the details of a mocap model
correct the thin shell for — mostly the smooth part between the markers — and, for a rig with
wrinkles, possibly all of it. Which part is measured on the cache itself: its deviation from the
shell's smooth solution for the same handles, e = cache − shell, and the model's details
D = Σ_b D_b are split into the same frequency bands, and per band the amplitudes are compared over
the cache's frames (:func:`bands_to_add`): where the cache's deviation has a good part of the
details' amplitude, the rig has content of its own at that scale and the band is not added again;
where the cache is as smooth as the shell (a rig without wrinkles, the fine bands), the band is
added whole. A cache the shell itself made (e = 0) gets every band. The chosen bands are taken
out of the detail model once (:func:`banded_detail_model`): a replay evaluates every frame as usual.

The bands come from screened-Poisson low-passes L_ℓ D = (M + ℓ² K)⁻¹ M D (K the cotangent
stiffness, M the lumped mass): a heat-kernel-like smoothing over the length ℓ, the same on any mesh
resolution, so the bands are set by lengths (multiples of the marker spacing), not by vertex counts.

The low-passes share one factor, factored again (numerically only: the same pattern) when the band
edge changes, and are solved for all frames and coordinates of a batch in one multi-right-hand-side call, in single
precision where PARDISO is available (``single=True``, what a replay uses): the details are float32
in the outputs, and the single-precision solve (to ~1e-6 of the details' amplitude) is several
times quicker at the paper's mesh sizes, where the solve's memory traffic is what costs.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import scipy.sparse as sp

from facepipe.core.psd import DetailModel, kernel_matrix, solve_rbf
from facepipe.core.shell import CholeskyFactor, cotmatrix, massmatrix
from facepipe.core.strain_details import StrainDetailModel, fit_strain_details

#: Cut-off wavelengths of the band edges in marker spacings, half-octave steps up to two spacings
#: (wrinkles are finer than the markers can see; what the shell misses between markers is at one
#: to two spacings) and an octave beyond.
BAND_WAVELENGTHS = (0.35, 0.5, 0.71, 1.0, 1.41, 2.0, 4.0)
#: A band is carried by the cache when its deviation from the shell there has at least this
#: fraction of the details' amplitude (see :func:`bands_to_add`).
CARRIED_RATIO = 0.5


class DetailBands:
    """Band decomposition of (C, V, 3) displacement fields on one mesh.

    Parameters
    ----------
    vertices : (V, 3) the rest mesh; faces : (T, 3).
    spacing : the marker spacing (length units); the band edges are ``BAND_WAVELENGTHS`` × spacing.
    single : factor and solve the low-passes in single precision where PARDISO is available
        (:class:`facepipe.core.shell.CholeskyFactor`): results to ~1e-6 of the field's amplitude,
        several times quicker on large meshes; False: double precision.

    Attributes
    ----------
    wavelengths : (K,) band edges, finest first; there are K + 1 bands, band 0 the finest.
    """

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, spacing: float,
                 wavelengths: tuple = BAND_WAVELENGTHS, single: bool = False):
        self.single = single
        self.wavelengths = np.asarray(wavelengths, dtype=np.float64) * float(spacing)
        self._K = cotmatrix(vertices, faces)
        self._mass = massmatrix(vertices, faces)
        # one factor, of the level last used: every level's matrix has the same pattern, so a
        # change of level factors only the new values (PARDISO keeps its analysis: at 530k
        # vertices 0.2 s against 1.2 s for a factorisation from scratch), and one factor's memory
        self._factor: CholeskyFactor | None = None
        self._level: int | None = None

    @property
    def n_bands(self) -> int:
        return len(self.wavelengths) + 1

    def lowpass(self, level: int, D: np.ndarray) -> np.ndarray:
        """L_level D: the field smoothed below wavelength ``wavelengths[level]`` ((C, V, 3) or (V, 3)),
        in D's precision (float32 stays float32, anything else is float64)."""
        if level != self._level:
            ell = self.wavelengths[level] / (2.0 * np.pi)  # a wave of wavelength λ is halved where λ = 2πℓ
            A = sp.diags(self._mass) + ell**2 * self._K
            if self._factor is None:
                self._factor = CholeskyFactor(A, single=self.single)
            else:
                self._factor.refactor(A)
            self._level = level
        D = _as_float(D)
        V = D.shape[-2]
        # M D with every frame's coordinate a right-hand side, written straight into the solver's
        # column-major (V, C·3) layout (a C-ordered (C, 3, V) array) in one pass over the field
        rhs = np.multiply(np.swapaxes(D, -2, -1), self._mass.astype(D.dtype, copy=False), dtype=D.dtype)
        x = self._factor.solve(rhs.reshape(-1, V).T).astype(D.dtype, copy=False)
        return np.swapaxes(x.T.reshape(D.shape[:-2] + (3, V)), -2, -1)

    def split(self, D: np.ndarray) -> list[np.ndarray]:
        """The K + 1 bands of ``D`` (finest first); they sum to ``D``."""
        lows = [_as_float(D)] + [self.lowpass(k, D) for k in range(len(self.wavelengths))]
        return [lows[k] - lows[k + 1] for k in range(len(self.wavelengths))] + [lows[-1]]

    def paired_band_sums(self, D: np.ndarray, E: np.ndarray) -> np.ndarray:
        """:func:`band_sums` of the bands of two fields of one shape, (C, V, 3) each, without keeping
        every band: both low-passed in the same solves (their frames side by side as right-hand
        sides), band by band from the finest, holding two low-passes at a time."""
        D = _as_float(D)
        pair = np.concatenate([D, _as_float(E).astype(D.dtype, copy=False)])
        C = D.shape[0]
        sums = np.zeros((self.n_bands, 3))
        above = pair
        for k in range(self.n_bands):
            below = self.lowpass(k, pair) if k < len(self.wavelengths) else None
            band = above - below if below is not None else above
            sums[k] = band_sums([band[:C]], [band[C:]])[0]
            above = below
        return sums

    def combine(self, D: np.ndarray, weights: np.ndarray, atol: float = 1e-6) -> np.ndarray:
        """Σ_b weights[b] · D_b without splitting where neighbouring weights agree.

        Σ_b c_b D_b = c_0 D + Σ_{k≥1} (c_k − c_{k−1}) L_{k−1} D (telescoping the bands), so only the
        low-passes at which the weight changes are solved: none when all weights are equal.
        In D's precision (float32 stays float32).
        """
        c = np.asarray(weights, dtype=np.float64)
        D = _as_float(D)
        out = D.copy() if c[0] == 1.0 else D * D.dtype.type(c[0])
        for k in range(1, len(c)):
            step = c[k] - c[k - 1]
            if abs(step) > atol:
                low = self.lowpass(k - 1, D)  # a fresh array: scaled in place, no temporary of the field's size
                low *= D.dtype.type(step)
                out += low
        return out

    def close(self) -> None:
        if self._factor is not None:
            self._factor.close()
        self._factor, self._level = None, None


def _as_float(D) -> np.ndarray:
    """D as float32 when it is float32, else float64."""
    D = np.asarray(D)
    return D if D.dtype == np.float32 else D.astype(np.float64, copy=False)


def band_sums(detail_bands: list[np.ndarray], deviation_bands: list[np.ndarray]) -> np.ndarray:
    """Per band b: [|D_b|², |e_b|², ⟨e_b, D_b⟩] over every vertex and frame (sums to accumulate over chunks)."""
    return np.array([[float((d * d).sum()), float((e * e).sum()), float((e * d).sum())]
                     for d, e in zip(detail_bands, deviation_bands)])


def bands_to_add(sums: np.ndarray, carried_ratio: float = CARRIED_RATIO) -> dict:
    """Which bands of the details to add, from :func:`band_sums` over a cache's frames.

    A band is carried by the cache when its deviation from the shell there has at least
    ``carried_ratio`` of the details' amplitude, r_b = |e_b| / |D_b| ≥ ``carried_ratio``: the rig has
    content of its own at that scale and it wins (adding the model's would count it twice); a band
    the cache lacks (r_b small: it is as smooth as the shell there) is added whole. A band without
    detail energy is not added (nothing to add).

    Returns
    -------
    dict: ``ratio`` r_b, ``projection`` ⟨e_b, D_b⟩ / |D_b|² (how much of the details' own direction the
    cache has, for the report), ``added`` (0 or 1 per band), ``added_energy`` (the added bands' share of
    the details' energy).
    """
    sums = np.asarray(sums, dtype=np.float64)
    dd, ee, ed = sums[:, 0], sums[:, 1], sums[:, 2]
    live = dd > 1e-12 * max(float(dd.sum()), 1e-300)
    ratio = np.where(live, np.sqrt(ee / np.where(live, dd, 1.0)), np.inf)
    added = (live & (ratio < carried_ratio)).astype(np.float64)
    return {"ratio": ratio, "projection": np.where(live, ed / np.where(live, dd, 1.0), 0.0), "added": added,
            "added_energy": float((added * dd).sum() / max(float(dd.sum()), 1e-300))}



def banded_detail_model(bands: DetailBands, model: DetailModel, frames: np.ndarray, added: np.ndarray) -> DetailModel:
    """The detail model of the details' chosen bands, made once for a whole take.

    The model is fixed by its details at its basis poses (P values and the side condition
    Σ_p w_p = 0 determine the P weights and the constant of every vertex), and the fit is linear in
    them. So the examples' details D_p (the model's own values at its basis poses, the novelty
    gate left out) are split into bands once, Σ_b added_b (D_p)_b, and the model is fitted again
    to them (:func:`facepipe.core.psd.solve_rbf`, interpolation on the same kernel): the new model
    gives exactly the added bands at every basis pose — none at the rest pose, whose details are
    zero — with no band filter per frame. The fields are filtered as world vectors in ``frames``
    (world = F @ local; the rest surface's frames) and brought back to local coordinates.

    Between the basis poses it interpolates the filtered examples, where the per-frame filter
    would filter the interpolated details: the same for PSD (the kernel is shared by every vertex,
    so the filter commutes with the interpolation), close to it for WPSD, whose kernel varies over
    the vertices with the edge weights; the novelty gate scales the new model's details as it did
    the old's.

    Parameters
    ----------
    bands : the band decomposition of the mesh; model : the model (psd or wpsd);
    frames : (V, 3, 3) local frames; added : (n_bands,) weight of each band (1: added, 0: left out).
    """
    basis = model.basis_features
    local = _banded_examples(bands, replace(model, gate=None).evaluate(basis), frames, added)  # (P, V, 3)
    phi = kernel_matrix(model.method, basis, basis, model.alpha)
    if phi.ndim == 3:
        phi = np.moveaxis(phi, 1, 0)  # (V, P, P)
    weights, const = solve_rbf(phi, local)
    return replace(model, weights=weights.astype(model.weights.dtype, copy=False),
                   const=const.astype(model.const.dtype, copy=False))


def banded_strain_model(bands: DetailBands, model: StrainDetailModel, frames: np.ndarray,
                        added: np.ndarray) -> StrainDetailModel:
    """:func:`banded_detail_model` for the local-strain model: its training details (exactly
    recovered from its weights, :meth:`StrainDetailModel.training_details`) split into bands once,
    the added ones kept, and the per-vertex kernel regressions fitted again to them with the same
    width and ridge. Linear in the training details, so between the training poses the new model
    is the per-frame filter of the old one to the extent that the filter commutes with the kernel
    (exactly where every vertex's neighbourhood shares its training strains)."""
    local = _banded_examples(bands, model.training_details(), frames, added)
    return fit_strain_details(np.moveaxis(model.samples, 1, 0), local, model.width, model.ridge)


def _banded_examples(bands: DetailBands, examples: np.ndarray, frames: np.ndarray, added: np.ndarray) -> np.ndarray:
    """Examples' details (P, V, 3) in local coordinates, pose 0 the rest pose: their added bands,
    filtered as world vectors in ``frames`` (world = F @ local) and brought back; the rest pose's
    details are zero by construction."""
    world = np.einsum("vij,pvj->pvi", frames, examples)
    local = np.einsum("vji,pvj->pvi", frames, bands.combine(world, added))
    local[0] = 0.0
    return local
