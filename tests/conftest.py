"""Shared test fixtures: small analytic meshes and the location of the ICT kit."""

from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared"
ICT = SHARED / "data" / "ict"


def ict_or_skip() -> Path:
    """The ICT kit folder, or skip: CI has ../shared beside the checkout, a fresh clone may not."""
    if not (ICT / "neutral.obj").is_file():
        pytest.skip(f"ICT kit not found at {ICT} (../shared is not beside this checkout)")
    return ICT


def grid(nx: int = 12, ny: int = 10, curved: bool = True, size: float = 10.0):
    """A triangulated (nx × ny)-vertex sheet, optionally bent like a cylinder patch.

    Returns vertices (V, 3) float64 and faces (T, 3) int64.
    """
    u, v = np.meshgrid(np.linspace(0, 1, nx), np.linspace(0, 1, ny), indexing="xy")
    x = size * (u - 0.5)
    y = size * (v - 0.5)
    z = -0.08 * size * (2 * u - 1) ** 2 if curved else np.zeros_like(x)
    V = np.stack([x, y, z], axis=-1).reshape(-1, 3)
    idx = np.arange(nx * ny).reshape(ny, nx)
    a, b, c, d = idx[:-1, :-1], idx[:-1, 1:], idx[1:, 1:], idx[1:, :-1]
    F = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])
    return V, F


@pytest.fixture
def sheet():
    return grid()
