"""The eye cards' motion check (facepipe.core.card_motion): shifts of known size recovered, and
which shifts count as the card's own motion."""

import numpy as np
import pytest
from scipy.ndimage import gaussian_filter, shift as nd_shift

from facepipe.core.card_motion import ALONG_COSINE, CardMotion, card_motion, masked_shifts, moves_along

SIZE = 16


def _field(seed=0):
    """A smooth random image (64 × 64) and its 16 × 16 window at (20, 20)."""
    big = gaussian_filter(np.random.default_rng(seed).normal(size=(64, 64)), 2.0)
    return big, big[20:20 + SIZE, 20:20 + SIZE]


def _moved(big, dx, dy):
    """The window of ``big`` whose content is the reference's moved by (dx, dy) texels:
    patch(p + shift) = reference(p)."""
    return nd_shift(big, (dy, dx), order=3)[20:20 + SIZE, 20:20 + SIZE]


@pytest.mark.parametrize("dx, dy", [(0.0, 0.0), (2.0, -1.0), (-3.0, 4.0), (1.5, 0.25), (-0.3, -2.6)])
def test_masked_shifts_recover_a_known_shift(dx, dy):
    big, reference = _field()
    seen = np.ones((SIZE, SIZE), dtype=bool)
    got = masked_shifts(reference, seen, _moved(big, dx, dy), seen, SIZE // 2)
    np.testing.assert_allclose(got, [dx, dy], atol=0.08)  # the parabola's sub-texel peak on a smooth field


def test_masked_shifts_use_only_what_both_see():
    big, reference = _field(1)
    patch = _moved(big, 2.0, 1.0)
    seen = np.ones((SIZE, SIZE), dtype=bool)
    covered = seen.copy()
    covered[:6] = False  # a lid over the top third of the frame's patch: its texels are other content
    patch = np.where(covered, patch, 5.0)
    np.testing.assert_allclose(masked_shifts(reference, seen, patch, covered, SIZE // 2), [2.0, 1.0], atol=0.1)
    # frames and several at once: the same numbers
    both = masked_shifts(reference, seen, np.stack([patch, reference]), np.stack([covered, seen]), SIZE // 2)
    np.testing.assert_allclose(both, [[2.0, 1.0], [0.0, 0.0]], atol=0.1)


def test_masked_shifts_are_nan_where_too_little_is_seen():
    big, reference = _field(2)
    seen = np.ones((SIZE, SIZE), dtype=bool)
    sliver = np.zeros((SIZE, SIZE), dtype=bool)
    sliver[:3] = True  # under the least overlap at every shift
    assert np.isnan(masked_shifts(reference, seen, _moved(big, 1.0, 0.0), sliver, SIZE // 2)).all()


def _motion(layers=((1.2, 0.0), (2.5, 0.3), (5.0, 0.5)), rest=((0.1, 1.5),)):
    big, reference = _field()
    return card_motion(reference, np.ones((SIZE, SIZE), dtype=bool), np.vstack([[0.0, 0.0], layers]), np.array(rest))


def test_card_motion_from_layers_and_rest_examples():
    motion = _motion(rest=((0.1, 1.5), (0.05, -0.02), (np.nan, np.nan)))
    assert motion.least == pytest.approx(0.6)  # half the first layer's 1.2 texels
    np.testing.assert_allclose(np.linalg.norm(motion.layers, axis=1), 1.0)
    np.testing.assert_allclose(motion.layers[0], [1.0, 0.0])
    assert motion.rest.shape == (1, 2)  # the noise-sized and unmeasured examples make no line
    np.testing.assert_allclose(motion.rest[0], np.array([0.1, 1.5]) / np.hypot(0.1, 1.5))
    # a first layer that barely moves the content: no check (the Haar match alone)
    assert _motion(layers=((0.2, 0.0), (2.0, 0.0))) is None
    assert _motion(layers=((np.nan, np.nan), (2.0, 0.0))) is None


def test_what_counts_as_the_cards_own_motion():
    motion = _motion()
    shifts = np.array([
        [2.0, 0.1],     # along the layers: counts
        [0.4, 0.0],     # along, but shorter than half the first layer: noise
        [0.2, 1.3],     # along an at-rest line (a look up)
        [-0.2, -1.3],   # the same line the other way (a lid closing over it): still not the card's motion
        [-2.0, 0.0],    # against the layers' sense
        [1.0, 1.4],     # beyond 45° of every layer's direction
        [np.nan, np.nan],  # not measured: the Haar reading stands
    ])
    np.testing.assert_array_equal(moves_along(shifts, motion), [True, False, False, False, False, False, True])
    # the 45° bound without any at-rest line
    free = CardMotion(motion.reference, motion.reference_seen, 0.5, np.array([[1.0, 0.0]]), np.zeros((0, 2)))
    angle = np.arccos(ALONG_COSINE)
    inside, outside = angle - 0.05, angle + 0.05
    pair = 2.0 * np.array([[np.cos(inside), np.sin(inside)], [np.cos(outside), np.sin(outside)]])
    np.testing.assert_array_equal(moves_along(pair, free), [True, False])
