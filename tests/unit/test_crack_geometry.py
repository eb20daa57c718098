"""Crack measurement against drawn cracks of known geometry: lengths, widths, orientation, counts,
histogram, and matching between load stages."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from workers.algorithms.cracks import (
    Crack,
    crack_coverage,
    darkening,
    length_histogram,
    match_cracks,
    measure_cracks,
    smooth_path,
    summarise_cracks,
    thin,
)

SHAPE = (400, 400)


def band_mask(points: np.ndarray, width: float, shape: tuple[int, int] = SHAPE) -> np.ndarray:
    """(H, W) bool: pixels whose centre lies closer than ``width / 2`` to the polyline ``points`` (N, 2) (x, y).

    An exact rasterisation of a crack of known centreline and width (cv2's thick lines are not: their
    thickness steps by 2 px).
    """
    p = np.asarray(points, dtype=np.float64)
    out = np.zeros(shape, dtype=bool)
    r = width / 2
    for a, b in zip(p[:-1], p[1:], strict=True):
        lo = np.maximum(np.floor(np.minimum(a, b) - r - 1).astype(int), 0)
        hi = np.minimum(np.ceil(np.maximum(a, b) + r + 1).astype(int), [shape[1] - 1, shape[0] - 1])
        ys, xs = np.mgrid[lo[1] : hi[1] + 1, lo[0] : hi[0] + 1]
        q = np.stack([xs, ys], axis=-1).astype(np.float64)
        d = b - a
        t = np.clip(((q - a) @ d) / max(float(d @ d), 1e-12), 0, 1)
        out[lo[1] : hi[1] + 1, lo[0] : hi[0] + 1] |= np.linalg.norm(q - (a + t[..., None] * d), axis=-1) < r
    return out


def segment(centre: tuple[float, float], length: float, angle_deg: float) -> np.ndarray:
    """(2, 2) end points (x, y) of a segment at ``angle_deg`` counter-clockwise from +x with y up."""
    a = np.radians(angle_deg)
    half = length / 2 * np.array([np.cos(a), -np.sin(a)])
    return np.array([np.asarray(centre) - half, np.asarray(centre) + half])


def arc(centre: tuple[float, float], radius: float, start: float, sweep: float, n: int = 400) -> np.ndarray:
    t = np.linspace(start, start + sweep, n)
    return np.column_stack([centre[0] + radius * np.cos(t), centre[1] + radius * np.sin(t)])


# A generic sub-pixel offset, as in a real raster: a centreline through pixel centres on a diagonal
# rasterises to a band up to 0.7 px wider or narrower than nominal (rows of centres 0.71 px apart).
OFFSET = np.array([0.31, 0.07])


@pytest.mark.parametrize("width", [1, 2, 3, 4, 5, 6])
def test_straight_cracks_at_any_angle(width: int) -> None:
    mm_per_px = 0.25
    for angle in (0, 10, 22.5, 30, 45, 60, 67.5, 80, 90, 112.5, 135, 157.5, 170):
        ends = segment((200, 200), 200, angle) + OFFSET
        cracks = measure_cracks(band_mask(ends, width), mm_per_px)
        assert len(cracks) == 1, angle
        c = cracks[0]
        assert abs(c.length_mm / (200 * mm_per_px) - 1) < 0.05, (angle, c.length_mm)
        assert abs(c.mean_width_mm / mm_per_px - width) <= 0.5, (angle, c.mean_width_mm)
        assert abs(c.max_width_mm / mm_per_px - width) <= 0.5, (angle, c.max_width_mm)
        assert abs((c.orientation_deg - angle + 90) % 180 - 90) < 2.0, (angle, c.orientation_deg)
        assert len(c.paths_mm) == 1 and c.endpoints_mm.shape == (2, 2)
        # each true end has a measured end within the crack's half-width plus 2 px
        gaps = np.linalg.norm(c.endpoints_mm[:, None] / mm_per_px - ends[None], axis=-1).min(axis=0)
        assert gaps.max() < width / 2 + 2, (angle, gaps)


@pytest.mark.parametrize("radius", [30, 60, 120])
@pytest.mark.parametrize("width", [1, 3, 6])
def test_curved_cracks(radius: float, width: int) -> None:
    points = arc((200, 200), radius, 0.2, 1.2 * np.pi) + OFFSET
    (c,) = measure_cracks(band_mask(points, width), 1.0)
    assert abs(c.length_mm / (radius * 1.2 * np.pi) - 1) < 0.05
    assert abs(c.mean_width_mm - width) <= 0.5
    assert abs(c.max_width_mm - width) <= 0.5


def test_width_follows_a_widening_crack() -> None:
    """A crack 2 px wide on its left half and 6 px on its right: max near 6, mean near 4."""
    mask = band_mask(np.array([[50, 200.3], [200, 200.3]]), 2) | band_mask(np.array([[200, 200.3], [350, 200.3]]), 6)
    (c,) = measure_cracks(mask, 1.0)
    assert abs(c.max_width_mm - 6) <= 0.5
    assert abs(c.mean_width_mm - 4) <= 0.5
    assert abs(c.length_mm - 300) < 0.05 * 300


def test_skeleton_is_thin_and_keeps_components() -> None:
    from scipy import ndimage as ndi

    mask = band_mask(arc((200, 200), 80, 0, 1.5 * np.pi) + OFFSET, 7) | band_mask(segment((100, 80), 120, 35), 4)
    mask[300:340, 40:120] = True  # a blob
    skeleton = thin(mask)
    eight = np.ones((3, 3))
    assert ndi.label(skeleton, eight)[1] == ndi.label(mask, eight)[1] == 3
    assert not np.any(skeleton & ~mask)
    # no 2x2 block survives (an 8-thin skeleton has none)
    blocks = skeleton[:-1, :-1] & skeleton[1:, :-1] & skeleton[:-1, 1:] & skeleton[1:, 1:]
    assert not blocks.any()


def test_branched_crack_length_is_the_sum_of_its_arms() -> None:
    centre = np.array([200.3, 200.3])
    arms = [
        segment(tuple(centre + 50 * np.array([np.cos(np.radians(a)), -np.sin(np.radians(a))])), 100, a)
        for a in (10, 130, 250)
    ]
    mask = np.zeros(SHAPE, dtype=bool)
    for arm in arms:
        mask |= band_mask(arm, 3)
    (c,) = measure_cracks(mask, 1.0)
    assert abs(c.length_mm / 300 - 1) < 0.05
    assert len(c.endpoints_mm) == 3
    assert abs(c.mean_width_mm - 3) <= 0.5


def test_crossing_cracks_and_a_closed_ring() -> None:
    mask = band_mask(segment((120.3, 120.1), 160, 0), 3) | band_mask(segment((120.3, 120.1), 160, 90), 3)
    (cross,) = measure_cracks(mask, 1.0)
    assert abs(cross.length_mm / 320 - 1) < 0.05 and len(cross.endpoints_mm) == 4
    (ring,) = measure_cracks(band_mask(arc((280, 280), 50, 0, 2 * np.pi) + OFFSET, 3), 1.0)
    assert abs(ring.length_mm / (2 * np.pi * 50) - 1) < 0.05
    assert len(ring.endpoints_mm) == 0 and abs(ring.mean_width_mm - 3) <= 0.5


def test_bumps_on_a_wide_crack_are_not_branches() -> None:
    ends = segment((200, 200), 240, 20) + OFFSET
    mask = band_mask(ends, 6)
    for t in (0.3, 0.55, 0.8):  # half-discs on the edge, radius 4 px
        p = ends[0] + t * (ends[1] - ends[0]) + np.array([1.0, 3.0])
        mask |= band_mask(np.array([p, p + 0.01]), 8)
    (c,) = measure_cracks(mask, 1.0)
    assert len(c.endpoints_mm) == 2
    assert abs(c.length_mm / 240 - 1) < 0.05


def test_count_histogram_and_minimum_length() -> None:
    mask = np.zeros(SHAPE, dtype=bool)
    lengths = (20, 45, 90, 150, 300)
    for k, length in enumerate(lengths):
        mask |= band_mask(segment((200, 30 + 80 * k), length, 5 * k) + OFFSET, 1 + k)
    mask[10:13, 380:383] = True  # 3x3 speck: 1 mm long at most
    mm_per_px = 0.1
    cracks = measure_cracks(mask, mm_per_px, min_length_mm=1.5)
    assert len(cracks) == len(lengths)
    measured = sorted(c.length_mm for c in cracks)
    assert np.allclose(measured, np.array(lengths) * mm_per_px, rtol=0.05)
    edges = (0.0, 3.0, 10.0, 20.0, np.inf)
    assert length_histogram(cracks, edges).tolist() == [1, 2, 1, 1]
    summary = summarise_cracks(cracks, edges)
    assert summary.count == 5 and summary.histogram_counts.sum() == 5
    assert abs(summary.total_length_mm - sum(lengths) * mm_per_px) < 0.05 * sum(lengths) * mm_per_px
    assert abs(summary.max_width_mm - 5 * mm_per_px) <= 0.5 * mm_per_px
    assert len(measure_cracks(mask, mm_per_px)) == 6  # without the minimum, the speck is a crack too


def test_empty_mask_and_misuse() -> None:
    assert measure_cracks(np.zeros(SHAPE, dtype=bool), 0.1) == []
    summary = summarise_cracks([])
    assert summary.count == 0 and summary.total_length_mm == 0.0 and summary.histogram_counts.sum() == 0
    with pytest.raises(ValueError):
        measure_cracks(np.zeros((4, 4, 3), dtype=bool), 0.1)
    with pytest.raises(ValueError):
        measure_cracks(np.zeros(SHAPE, dtype=bool), 0.0)
    with pytest.raises(ValueError):
        length_histogram([], (1.0, 1.0))
    with pytest.raises(ValueError):
        match_cracks([], [], 0.0)


def test_smoothing_keeps_ends_and_straight_lines() -> None:
    line = np.column_stack([np.arange(20.0), 0.5 * np.arange(20.0)])
    assert np.allclose(smooth_path(line, 2.0), line)
    stairs = np.array([[i // 2 + i % 2, i // 2] for i in range(41)], dtype=np.float64)  # 1-px staircase
    smoothed = smooth_path(stairs, 2.0)
    assert np.allclose(smoothed[[0, -1]], stairs[[0, -1]])
    true = np.hypot(*(stairs[-1] - stairs[0]))
    raw = np.linalg.norm(np.diff(stairs, axis=0), axis=1).sum()
    assert raw > 1.3 * true  # 4-connected steps: ~sqrt(2) too long
    assert np.linalg.norm(np.diff(smoothed, axis=0), axis=1).sum() < 1.05 * true


def _stage(polylines: list[np.ndarray], width: float = 3) -> list[Crack]:
    mask = np.zeros(SHAPE, dtype=bool)
    for p in polylines:
        mask |= band_mask(p + OFFSET, width)
    return measure_cracks(mask, 0.1)


def test_match_cracks_between_load_stages() -> None:
    a_old = np.array([[40.0, 60.0], [180.0, 80.0]])
    a_new = np.array([[40.0, 60.0], [180.0, 80.0], [240.0, 110.0]])  # grew by hypot(60, 30) = 67.1 px
    b = arc((250, 250), 60, 0.0, 2.0)
    c_new = segment((100, 300), 80, 70)
    previous = _stage([a_old, b])
    current = _stage([a_new, b + np.array([1.0, -1.0]), c_new])  # b re-photographed 1.4 px off
    assert len(previous) == 2 and len(current) == 3
    by_start = {tuple(np.round(c.bbox_mm[:2])): i for i, c in enumerate(current)}
    matches = match_cracks(previous, current, tolerance_mm=0.3)
    status = {m.current: m for m in matches}
    grown = status[by_start[(4.0, 6.0)]]
    assert grown.status == "grown" and grown.previous == (0,)
    assert abs(grown.growth_mm - 6.708) < 0.05 * 6.708
    unchanged = [m for m in matches if m.previous == (1,)]
    assert len(unchanged) == 1 and unchanged[0].status == "unchanged" and unchanged[0].growth_mm < 0.3
    new = [m for m in matches if m.status == "new"]
    assert len(new) == 1 and new[0].previous == () and abs(new[0].growth_mm - 8.0) < 0.05 * 8.0


def test_two_cracks_that_join_count_as_one_grown_crack() -> None:
    left, right = np.array([[40.0, 200.0], [150.0, 190.0]]), np.array([[200.0, 185.0], [330.0, 170.0]])
    bridge = np.array([[150.0, 190.0], [200.0, 185.0]])
    previous = _stage([left, right])
    (joined,) = match_cracks(previous, _stage([left, bridge, right]), tolerance_mm=0.3)
    assert joined.status == "grown" and joined.previous == (0, 1)
    assert abs(joined.growth_mm - 5.025) < 0.05 * 5.025 + 0.1
    # far outside the tolerance nothing matches
    moved = _stage([left + np.array([0.0, 40.0])])
    assert [m.status for m in match_cracks(previous, moved, tolerance_mm=0.3)] == ["new"]


@pytest.mark.parametrize(("width", "tolerance"), [(1.6, 1.0), (3.0, 0.35), (5.5, 0.35)])
def test_width_from_darkness_not_from_a_fat_mask(width: float, tolerance: float) -> None:
    """A dark line of known width, blurred (sigma 0.8 px) and noisy on a lit coating; the detector's mask
    is 4 px too wide on each side. Widths from the mask's area are that much too wide; from the darkening,
    right to 0.35 px, except for a line too thin for its full depth to show through the blur."""
    rng = np.random.default_rng(1)
    line = segment((200, 200), 260, 25)
    # the share of each pixel the line covers, from a 4x supersampled rasterisation
    fine = band_mask(line * 4 + 1.5, width * 4, (SHAPE[0] * 4, SHAPE[1] * 4))
    share = fine.reshape(SHAPE[0], 4, SHAPE[1], 4).mean(axis=(1, 3))
    light = np.linspace(0.7, 1.2, SHAPE[1])[None, :]  # a light ramp across the coating
    grey = 160.0 * light * (1 - 0.45 * share)
    grey = cv2.GaussianBlur(grey.astype(np.float32), (0, 0), 0.8) + rng.normal(0, 2.0, SHAPE).astype(np.float32)
    fat = band_mask(line, width + 8.0)
    coverage = crack_coverage(darkening(grey, fat, background_px=12.0), fat)
    (by_mask,) = measure_cracks(fat, 1.0)
    (by_darkness,) = measure_cracks(fat, 1.0, coverage=coverage)
    assert by_mask.mean_width_mm > width + 6.0
    assert abs(by_darkness.mean_width_mm - width) < tolerance, by_darkness.mean_width_mm


def test_widths_below_photo_resolution_are_flagged_and_resolved_ones_kept() -> None:
    """A profile width under 1.7 photo px is flagged: its (equivalent) width is kept, with an interval that
    holds every width from 0 to 1.7 px; a wider one is kept, with an uncertainty that grows with the width and
    stays a fraction of a photo pixel."""
    from workers.algorithms.cracks import estimate_width

    p = 0.4  # mm per photo pixel
    for width_px in (0.3, 1.0, 1.65):
        low = estimate_width(width_px * p, p)
        assert low.below_photo_resolution and low.width_mm == pytest.approx(width_px * p)
        assert low.width_mm - low.uncertainty_mm <= 1e-12 and low.width_mm + low.uncertainty_mm >= 1.7 * p - 1e-12
    previous = 0.0
    for width_px in (1.75, 2.0, 3.0, 5.0):
        estimate = estimate_width(width_px * p, p)
        assert not estimate.below_photo_resolution and estimate.width_mm == pytest.approx(width_px * p)
        assert previous < estimate.uncertainty_mm < 0.5 * p
        previous = estimate.uncertainty_mm
    with pytest.raises(ValueError):
        estimate_width(1.0, 0.0)
