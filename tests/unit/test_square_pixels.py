"""A strip at exactly 50 % forward overlap: no ground is seen three times, so the tie points leave each frame's
width free and GPS fixes only its centre. align_frames' square-pixel prior (``strip_square_pixels``) shapes the
frames; without it the strip comes out hundreds of px out of true.

Frames are the strip generator's true homographies (``tests.strip_scenes``), tie points drawn from them with
0.1 px noise, GPS fixes of the frame centres with 1 m noise: the adjustment is all that is tested.
"""

from __future__ import annotations

import numpy as np
import pytest

from tests.strip_scenes import adjustment_inputs
from tests.unit.test_level_plane import corner_errors
from workers.algorithms.mosaic import TiePoints
from workers.algorithms.mosaic.plane_adjustment import aspect_shear, aspect_shear_derivative
from workers.config import MosaicConfig
from workers.records import Frame
from workers.stages.align_frames import adjust_plane

SIZE = (20_000, 480)  # a strip frame at a quarter of the camera's width, px
FRAMES = 120
ROOT = FRAMES // 2
GSD_M = 0.25 * 75_000 / SIZE[0]  # the full camera's ground: 1 m GPS noise is 4 of its px, 1 of these
GPS_NOISE_M = 1.0


def _strip(
    seed: int, overlap: float = 0.5, count: int = FRAMES
) -> tuple[list[np.ndarray], dict[int, Frame], dict[tuple[int, int], TiePoints], dict]:
    """Truth (frame -> ground px), frames with noisy GPS, tie points of consecutive frames (400 of 0.1 px), the
    chained start (from frame ``count // 2``)."""
    return adjustment_inputs(seed, count, SIZE, overlap, GSD_M, gps_noise_m=GPS_NOISE_M)


@pytest.mark.parametrize("seed", [0, 1])
def test_square_pixels_keep_a_strip_at_50_percent_overlap_true(seed: int) -> None:
    truth, frames, ties, start = _strip(seed)
    free = corner_errors(
        adjust_plane(MosaicConfig(mode="strip", strip_square_pixels=0), frames, start, ROOT, ties), truth, SIZE
    )
    held = corner_errors(adjust_plane(MosaicConfig(mode="strip"), frames, start, ROOT, ties), truth, SIZE)
    # the frames' widths wander with nothing to hold them (16-17 px); the prior holds them to the GPS's
    # along-track scale (3.9 px, at the end frames, whose far half no other frame sees; 1.1-1.4 px RMS)
    assert free.max() > 12.0, free.max()
    assert held.max() < 0.4 * free.max() and np.sqrt(np.mean(held**2)) < 1.5, (held.max(), np.sqrt(np.mean(held**2)))


def test_the_prior_leaves_drone_flights_alone() -> None:
    truth, frames, ties, start = _strip(2)
    planar = MosaicConfig(mode="planar", perspective_damping=0.0)
    unprimed = MosaicConfig(mode="strip", strip_square_pixels=0)
    # the planar mode's frames are tilted photos: the same adjustment as a strip without the prior
    a, b = adjust_plane(planar, frames, start, ROOT, ties), adjust_plane(unprimed, frames, start, ROOT, ties)
    assert max(np.abs(a[k] - b[k]).max() for k in a) < 1e-9


def test_aspect_and_shear_are_the_frame_pixels_own() -> None:
    # a frame normalised isotropically keeps its pixels' shape: squeezed by 2 % in y, sheared by 1 %
    M = np.array([[[1.0, 0.01, 5.0], [0.01, 0.98, 3.0], [0.0, 0.0, 1.0]]])
    value = aspect_shear(M)
    np.testing.assert_allclose(value, [[0.02 / 1.98, 0.02 / 1.98]], rtol=1e-12)
    # a rotation and a scale change nothing
    c, s = 2.0 * np.cos(0.3), 2.0 * np.sin(0.3)
    np.testing.assert_allclose(aspect_shear(np.array([[[c, -s, 1.0], [s, c, 2.0], [0, 0, 1]]])), 0, atol=1e-15)


def test_the_derivatives_are_the_finite_differences() -> None:
    rng = np.random.default_rng(0)
    A = np.eye(3) + rng.normal(0, 0.1, (5, 3, 3))
    D = rng.normal(0, 0.05, (5, 8))

    def corrected(D: np.ndarray) -> np.ndarray:
        return A @ (np.eye(3) + np.pad(D, ((0, 0), (0, 1))).reshape(-1, 3, 3))

    _, analytic = aspect_shear_derivative(corrected(D), A)
    step = 1e-6 * np.eye(8)
    numeric = np.stack(
        [(aspect_shear(corrected(D + e)) - aspect_shear(corrected(D - e))) / 2e-6 for e in step], axis=-1
    )
    np.testing.assert_allclose(analytic, numeric, atol=1e-8)
