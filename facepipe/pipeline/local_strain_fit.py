"""The local-strain detail model of a rig (``[psd] method = "local_strain"``): the training poses'
large-scale surfaces, their per-vertex local strain, and the per-vertex kernel regressions of the
details over it (:mod:`facepipe.core.strain_details`)."""

from __future__ import annotations

import numpy as np

from facepipe.core.local_strain import StrainOperator, vertex_strain
from facepipe.core.shell import large_scale_positions
from facepipe.core.strain_details import StrainDetailModel, fit_strain_details


def large_scale_strains(geo, handle_positions: np.ndarray, op: StrainOperator | None = None,
                        chunk: int = 16) -> np.ndarray:
    """Local strain (E, V, 3) of the large-scale surfaces that handle positions (E, H, 3) drive."""
    op = op or StrainOperator.of(geo.rest, geo.faces, geo.neighbors)
    out = np.empty((handle_positions.shape[0],) + geo.rest.shape)
    rest_handles = geo.rest[geo.handles]
    for s in range(0, handle_positions.shape[0], chunk):
        large = large_scale_positions(geo.rest, geo.B, handle_positions[s:s + chunk] - rest_handles)
        out[s:s + chunk] = vertex_strain(large, op)
    return out


def fit_local_strain(geo, handle_positions: np.ndarray, details: np.ndarray, width: float,
                     ridge: float) -> StrainDetailModel:
    """The local-strain model of training poses given by their handle positions (E, H, 3) (pose 0:
    rest) and their details (E, V, 3) in the large-scale surfaces' local frames
    (:meth:`facepipe.pipeline.fit.Geometry.details`)."""
    return fit_strain_details(large_scale_strains(geo, handle_positions), details, width, ridge)
