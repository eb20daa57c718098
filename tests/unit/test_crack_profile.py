"""Crack widths from cross-section profiles: a dark line of known width and contrast, covered exactly (4x
supersampled), blurred and noisy on a lit coating, found by a mask that is too wide."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from tests.unit.test_crack_geometry import SHAPE, band_mask, segment
from workers.algorithms.cracks import (
    crack_widths,
    fit_blurred_line,
    measure_cracks,
    profile_widths,
    reference_contrast,
    resolved,
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
    contrast = reference_contrast([[fit], [wide]], [1.0, 1.0])
    assert contrast is not None and abs(contrast - CONTRAST) < 0.02
    (estimate,) = crack_widths([fit], 1.0, contrast)
    assert abs(estimate - width) < 0.12, estimate
    (measured,) = with_widths([crack], np.array([estimate]))
    assert measured.mean_width_mm == pytest.approx(estimate) and measured.max_width_mm >= estimate
    assert measured.length_mm == crack.length_mm  # widths only


def test_no_fit_without_samples_and_misuse() -> None:
    grey = np.full(SHAPE, 150.0, np.float32)
    empty = np.zeros(SHAPE, bool)
    assert profile_widths(grey, empty, [[np.array([[10.0, 10.0], [20.0, 10.0]])]]) == [None]
    assert fit_blurred_line(np.zeros(5), np.zeros(5)) is None
    assert np.isnan(crack_widths([None], 1.0, 0.3)).all()
    with pytest.raises(ValueError):
        profile_widths(grey, empty[:10], [])
    with pytest.raises(ValueError):
        crack_widths([None], 0.0, None)
    with pytest.raises(ValueError):
        reference_contrast([[None]], [1.0, 2.0])
