"""A strip at exactly 50 % forward overlap: no ground is seen three times, so the tie points leave each frame's
width free and GPS fixes only its centre. align_frames' square-pixel prior (``strip_square_pixels``) shapes the
frames; without it the strip comes out several px out of true (at the camera's full width, 14 px against 3-5).

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
    # the frames' widths wander with only the tie points to hold them (3.4-3.6 px, 1.2-1.7 px RMS; at the full
    # camera's width 14 px); the prior holds them to the GPS's along-track scale (2.1 px, 0.6-0.9 px RMS)
    free_rms, held_rms = np.sqrt(np.mean(free**2)), np.sqrt(np.mean(held**2))
    assert held.max() < 0.75 * free.max() and held_rms < 0.6 * free_rms, (held.max(), free.max(), held_rms, free_rms)
    assert held.max() < 2.5 and held_rms < 1.0, (held.max(), held_rms)


@pytest.mark.parametrize("seed", [0, 1])
def test_more_tie_points_make_a_strip_truer(seed: int) -> None:
    # The adjustment counts a tie point's miss in the photos' pixels. Counted in the plane's, each point pulled
    # its frames smaller by its noise's variance (a smaller frame, a smaller miss), and the pulls of 3200 points
    # per pair bent a 40-frame strip further than 400 did: 1.3-1.5 px against 0.6-1.2. Now 0.4-0.45 against 0.5-0.55.
    errors = []
    for count in (400, 3200):
        truth, frames, ties, start = adjustment_inputs(
            seed, 40, SIZE, 0.5, GSD_M, ties_per_pair=count, gps_noise_m=GPS_NOISE_M
        )
        errors.append(corner_errors(adjust_plane(MosaicConfig(mode="strip"), frames, start, 20, ties), truth, SIZE))
    assert errors[1].max() < 0.6 and errors[1].max() < errors[0].max(), [e.max() for e in errors]


def test_the_prior_leaves_drone_flights_alone() -> None:
    truth, frames, ties, start = _strip(2)
    unprimed = MosaicConfig(mode="strip", strip_square_pixels=0)
    # at the same inlier threshold: a planar job's grows with working copies over the default size, a strip's not
    scale = MosaicConfig(mode="planar").threshold_scale(max(SIZE))
    planar = MosaicConfig(
        mode="planar", perspective_damping=0.0, ransac_threshold_px=unprimed.ransac_threshold_px / scale
    )
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
