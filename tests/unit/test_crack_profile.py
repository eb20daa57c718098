"""Crack widths from cross-section profiles: a dark line of known width and contrast, covered exactly (4x
supersampled), blurred and noisy on a lit coating, found by a mask that is too wide."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from tests.unit.test_crack_geometry import SHAPE, band_mask, segment
from workers.algorithms.cracks import (
    ProfileFit,
    crack_widths,
    fit_blurred_line,
    line_like,
    measure_cracks,
    profile_widths,
    reference_contrast,
    resolved,
    sampling_across,
    with_widths,
)

CONTRAST = 0.35


def render_line(line: np.ndarray, width: float, blur: float, seed: int = 2) -> np.ndarray:
    """(H, W) float32 grey: a coating under a light ramp, ``line`` (N, 2) (x, y) px ``width`` px wide and
    ``CONTRAST`` darker, through a Gaussian PSF of ``blur`` px, with noise of 2 grey levels."""
    rng = np.random.default_rng(seed)
    fine = band_mask(line * 4 + 1.5, width * 4, (SHAPE[0] * 4, SHAPE[1] * 4))
    share = fine.reshape(SHAPE[0], 4, SHAPE[1], 4).mean(axis=(1, 3))
    light = np.linspace(0.7, 1.2, SHAPE[1])[None, :]
    grey = (160.0 * light * (1 - CONTRAST * share)).astype(np.float32)
    return cv2.GaussianBlur(grey, (0, 0), blur) + rng.normal(0, 2.0, SHAPE).astype(np.float32)


def fit_line(width: float, blur: float, angle: float = 25.0):  # type: ignore[no-untyped-def]
    line = segment((200, 200), 260, angle)
    grey = render_line(line, width, blur)
    mask = band_mask(line, width + 4.0)  # the detector's mask: where the crack is, not how wide
    (crack,) = measure_cracks(mask, 1.0)
    (fit,) = profile_widths(grey, mask, [list(crack.paths_mm)])
    return crack, fit


@pytest.mark.parametrize(("width", "angle"), [(3.0, 25.0), (5.0, 25.0), (3.5, 80.0), (8.0, 140.0)])
def test_resolved_line_width_contrast_and_blur(width: float, angle: float) -> None:
    _, fit = fit_line(width, 0.8, angle)
    assert fit is not None
    assert abs(fit.width_px - width) < 0.1, fit
    assert abs(fit.contrast - CONTRAST) < 0.02, fit
    # the PSF, widened a little by the 4x box of the supersampled cover and the centreline's wander
    assert 0.7 < fit.blur_px < 1.0, fit


@pytest.mark.parametrize("width", [1.0, 1.6])
def test_unresolved_line_keeps_its_darkness_deficit(width: float) -> None:
    """Through a PSF of 1.2 px a line of 1-1.6 px is the PSF's shape: its own fit may trade width for
    contrast, but their product (the deficit) holds, and over the contrast of a resolved line it is the
    width."""
    crack, fit = fit_line(width, 1.2)
    _, wide = fit_line(6.0, 1.2)
    assert fit is not None and wide is not None
    assert not resolved(fit, photo_px=1.0) and resolved(wide, photo_px=1.0)
    assert abs(fit.deficit_px / (CONTRAST * width) - 1) < 0.06, fit
    contrast = reference_contrast([[fit], [wide]], [[1.0], [1.0]], [[260.0], [260.0]])
    assert contrast is not None and abs(contrast - CONTRAST) < 0.02
    (estimate,) = crack_widths([fit], [1.0], contrast)
    assert abs(estimate - width) < 0.12, estimate
    (measured,) = with_widths([crack], np.array([estimate]))
    assert measured.mean_width_mm == pytest.approx(estimate) and measured.max_width_mm >= estimate
    assert measured.length_mm == crack.length_mm  # widths only


def test_no_fit_without_samples_and_misuse() -> None:
    grey = np.full(SHAPE, 150.0, np.float32)
    empty = np.zeros(SHAPE, bool)
    assert profile_widths(grey, empty, [[np.array([[10.0, 10.0], [20.0, 10.0]])]]) == [None]
    assert fit_blurred_line(np.zeros(5), np.zeros(5)) is None
    assert np.isnan(crack_widths([None], [1.0], 0.3)).all()
    assert reference_contrast([[None]], [[1.0]], [[10.0]]) is None
    with pytest.raises(ValueError):
        profile_widths(grey, empty[:10], [])
    with pytest.raises(ValueError):
        crack_widths([None], [0.0], None)
    with pytest.raises(ValueError):
        crack_widths([None], [1.0, 1.0], None)
    with pytest.raises(ValueError):
        reference_contrast([[None]], [[1.0], [2.0]], [[1.0]])


def fit_of(width: float, contrast: float, blur: float = 0.6) -> ProfileFit:
    return ProfileFit(width, contrast, blur, 0.0, 1000, 0.03)


def test_reference_contrast_is_the_long_measurable_cracks() -> None:
    """Only cracks at least 1.7 photo px wide speak for the coating's contrast (a narrower profile trades
    contrast for width), weighted by their length: one long crack outweighs two short ones."""
    fits = [[fit_of(3.0, 0.35), fit_of(2.0, 0.20), fit_of(2.2, 0.21)], [fit_of(1.0, 0.12), fit_of(4.0, 0.36)]]
    photo = [[1.0, 1.0, 1.0], [1.0, 1.0]]
    assert reference_contrast(fits, photo, [[100.0, 30.0, 30.0], [500.0, 50.0]]) == pytest.approx(0.35)
    assert reference_contrast(fits, photo, [[10.0, 30.0, 30.0], [500.0, 10.0]]) == pytest.approx(0.21)
    # across a crack seen along an oblique view a photo pixel spans more: the same fits are not wide enough
    assert reference_contrast(fits, [[2.0, 2.0, 2.0], [2.0, 2.0]], [[1.0] * 3, [1.0] * 2]) == pytest.approx(0.36)


def test_line_like_drops_blots_not_cracks() -> None:
    assert line_like(fit_of(2.0, 0.3, 0.6), 50.0, 5.0)  # a crack 50 px long (its mask is wider)
    assert line_like(fit_of(1.0, 0.3, 0.5), 25.0, 2.0)  # a hairline as short as the detector keeps
    assert not line_like(fit_of(6.0, 0.08, 1.0), 40.0, 6.0)  # a faint blot 40 px long and 6 wide
    assert not line_like(fit_of(0.5, 0.9, 2.5), 50.0, 3.0)  # a dark speck blurred over 6 px
    assert line_like(None, 30.0, 2.0) and not line_like(None, 20.0, 4.0)  # too short to fit: by its mask


def test_sampling_across_follows_the_crack_direction() -> None:
    """A photo pixel 0.1 mm across x and 0.2 mm along y (an oblique view from +y): a crack along x (normal y)
    is sampled at 0.2 mm per photo px across it, one along y at 0.1, a diagonal one at sqrt((0.01 + 0.04) / 2)."""
    footprint = np.zeros((20, 30, 3), np.float32)
    footprint[..., 0], footprint[..., 2] = 0.01, 0.04
    along_x = [np.column_stack([np.linspace(2, 20, 40), np.full(40, 5.0)])]
    along_y = [np.column_stack([np.full(40, 5.0), np.linspace(2, 15, 40)])]
    diagonal = [np.column_stack([np.linspace(2, 12, 40), np.linspace(2, 12, 40)])]
    assert sampling_across(along_x, footprint, 1.0) == pytest.approx(0.2, rel=1e-5)
    assert sampling_across(along_y, footprint, 1.0) == pytest.approx(0.1, rel=1e-5)
    assert sampling_across(diagonal, footprint, 1.0) == pytest.approx(np.sqrt(0.025), rel=1e-4)
    assert sampling_across(along_x, np.zeros_like(footprint), 1.0) is None  # no photo sees it
