"""Coarse registration of a strip frame pair, as the source work does it: Harris corners and NCC of
mean-centred windows on a pyramid level, a RANSAC homography, and the spread criterion (the inliers must
span enough of the overlap's long side in both frames), going one level finer with another Harris setting
until it holds."""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from gpu_kernels.backend import Device, get_array_module, to_device, to_host
from gpu_kernels.harris import harris_corners
from gpu_kernels.masks import shift_window
from gpu_kernels.ncc import match_ncc, window_descriptors
from workers.algorithms.mosaic.alignment import apply_homography
from workers.algorithms.mosaic.homography import estimate_homography
from workers.algorithms.strips.homography import refine_homography
from workers.algorithms.strips.ncc_search import ncc_peaks
from workers.algorithms.strips.overlap import spread_along
from workers.algorithms.strips.pyramid import FramePyramid

HARRIS_K = 0.04  # the source work's Harris constant
SUBPIXEL_SEARCH = 2  # level px searched around a coarse match for its sub-pixel NCC peak


@dataclass(frozen=True)
class HarrisSetting:
    """One detector setting tried: response ``threshold`` (8-bit input scaled to [0, 1]) and the
    non-maximum suppression ``radius``, px of the level."""

    threshold: float
    radius: int


# Tried in turn at every level: the second finds weaker, denser corners where the first found too few.
DEFAULT_SETTINGS = (HarrisSetting(1e-4, 3), HarrisSetting(1e-5, 2))


@dataclass(frozen=True)
class CoarseAttempt:
    """One (level, setting) tried: mutual NCC matches, RANSAC inliers among them and the spread they reached."""

    level: int
    setting: HarrisSetting
    matches: int
    inliers: int
    spread: float


@dataclass(frozen=True)
class CoarseRegistration:
    """Result of :func:`register_coarse`.

    Attributes
    ----------
    homography : (3, 3) float64 or None
        Frame a native px -> frame b native px, ``H[2, 2] = 1``; None when no attempt found a model.
    level : int or None
        The pyramid level the kept result was found on: the level this pair uses.
    setting : HarrisSetting or None
        The detector setting of the kept result.
    spread : float
        Min over both frames of the inliers' extent / the overlap's extent along the long axis.
    extent_px, overlap_px : tuple of float
        The inliers' and the overlap's extent along the long axis in a and in b, native px.
    points_a, points_b : (M, 2) float64
        The inliers, native px (x, y).
    satisfied : bool
        Whether ``spread >= min_spread``.
    reason : str
        Why this result was kept, for a report.
    attempts : tuple of CoarseAttempt
        Every attempt, in the order tried.
    """

    homography: np.ndarray | None
    level: int | None
    setting: HarrisSetting | None
    spread: float
    extent_px: tuple[float, float]
    overlap_px: tuple[float, float]
    points_a: np.ndarray
    points_b: np.ndarray
    satisfied: bool
    reason: str
    attempts: tuple[CoarseAttempt, ...]


@dataclass(frozen=True)
class CoarseOptions:
    """Parameters of one coarse attempt (the defaults suit levels 48-120 px across the short side)."""

    half_window: int = 7  # NCC window half side, level px: (2 h + 1)^2 windows
    ncc_threshold: float = 0.8  # least NCC of a match
    ransac_px: float = 1.0  # RANSAC inlier threshold, level px
    cell_px: int = 8  # corners are capped per cell of this side, so they spread over the frame
    per_cell: int = 2  # corners kept per cell
    max_points: int = 4000  # strongest corners kept per frame: bounds the NCC score matrix (64 MB)
    min_inliers: int = 12  # fewer RANSAC inliers count as no model
    prior_radius_px: float = 64.0  # with a prior homography: how far (native px) a match may lie from it


def feasible_levels(levels: Sequence[int], thin_px: float, options: CoarseOptions = CoarseOptions()) -> list[int]:
    """The ``levels`` (coarsest first) on which an overlap ``thin_px`` native px across its thinner side can hold a
    match: a corner's NCC window and its sub-pixel search inside both frames, ``2 (half_window + SUBPIXEL_SEARCH)``
    level px (18). A strip's frames two apart at 55 % overlap meet over 180 px: 5.6 px at level 5, 11 at level 4,
    where every attempt failed, 22 at level 3. The finest level when none can."""
    need = 2 * (options.half_window + SUBPIXEL_SEARCH)
    ordered = sorted(levels, reverse=True)
    return [level for level in ordered if thin_px / 2**level >= need] or ordered[-1:]


def register_coarse(
    pyramid_a: FramePyramid,
    pyramid_b: FramePyramid,
    min_spread: float = 0.5,
    levels: Sequence[int] | None = None,
    settings: Sequence[HarrisSetting] = DEFAULT_SETTINGS,
    prior: np.ndarray | None = None,
    options: CoarseOptions = CoarseOptions(),
    device: Device = "cpu",
) -> CoarseRegistration:
    """Register frame a to frame b coarse to fine, until the inliers satisfy the spread criterion.

    At each level (coarsest first) every Harris setting is tried: Harris corners (k = 0.04, 3x3 Sobel,
    3x3 Gaussian window; ``gpu_kernels.harris``), NCC of mean-centred windows with mutual best matches
    (``gpu_kernels.ncc``), a USAC homography (``cv2.findHomography``, MAGSAC++). The first attempt whose
    inliers span at least ``min_spread`` of the overlap's long side in both frames wins; when none does,
    the attempt whose spread came closest is kept (``satisfied`` False).

    Parameters
    ----------
    pyramid_a, pyramid_b : the two frames' reduced copies (:func:`build_pyramid`).
    min_spread : the spread criterion, a fraction of the overlap's long side (0.5: half of it).
    levels : levels to try, in order; by default every level both pyramids hold, coarsest first.
    settings : Harris settings tried at each level, in order.
    prior : (3, 3) native a px -> native b px, e.g. from GPS: corners are then matched only within
        ``options.prior_radius_px`` of where it predicts them (``gpu_kernels.masks.shift_window``), and only
        corners it predicts inside the other frame take part. None: all against all.
    device : ``cpu`` or ``cuda``: where Harris and NCC run; RANSAC runs on the host.

    Returns
    -------
    CoarseRegistration
    """
    if not 0 < min_spread <= 1:
        raise ValueError(f"min_spread must be in (0, 1], got {min_spread}")
    if levels is None:
        common = sorted(set(pyramid_a.levels) & set(pyramid_b.levels), reverse=True)
        levels = common
    if not levels or not settings:
        raise ValueError("register_coarse needs at least one level and one Harris setting")
    attempts: list[CoarseAttempt] = []
    best: CoarseRegistration | None = None
    for level in levels:
        for setting in settings:
            result, matches = _attempt(pyramid_a, pyramid_b, level, setting, min_spread, prior, options, device)
            attempts.append(CoarseAttempt(level, setting, matches, len(result.points_a), result.spread))
            if best is None or (result.spread, len(result.points_a)) > (best.spread, len(best.points_a)):
                best = result
            if result.satisfied:
                return _with_trail(result, attempts, f"spread {result.spread:.2f} >= {min_spread:.2f}")
    assert best is not None
    if best.homography is None:
        return _with_trail(best, attempts, "no attempt found a homography")
    return _with_trail(
        best, attempts, f"no setting reached spread {min_spread:.2f}; kept the closest ({best.spread:.2f})"
    )


def _with_trail(result: CoarseRegistration, attempts: list[CoarseAttempt], why: str) -> CoarseRegistration:
    where = f" at level {result.level}" if result.level is not None else ""
    reason = f"{why}{where} after {len(attempts)} attempt(s)"
    return dataclasses.replace(result, reason=reason, attempts=tuple(attempts))


def _attempt(
    pyramid_a: FramePyramid,
    pyramid_b: FramePyramid,
    level: int,
    setting: HarrisSetting,
    min_spread: float,
    prior: np.ndarray | None,
    options: CoarseOptions,
    device: Device,
) -> tuple[CoarseRegistration, int]:
    """One (level, setting): the registration it gives (``homography`` None when it fails) and its matches."""
    S_a, S_b = pyramid_a.to_level(level), pyramid_b.to_level(level)
    image_a, image_b = to_device(pyramid_a.image(level), device), to_device(pyramid_b.image(level), device)
    prior_level = None if prior is None else S_b @ prior @ np.linalg.inv(S_a)
    pts_a, pts_b = _match_level(image_a, image_b, setting, prior_level, options, S_b[0, 0])
    failed = _failure(level, setting)
    if len(pts_a) < options.min_inliers:
        return failed, len(pts_a)
    H_level, inliers = estimate_homography(pts_a, pts_b, options.ransac_px)
    if H_level is None or inliers.sum() < options.min_inliers:
        return failed, len(pts_a)
    full_a = apply_homography(np.linalg.inv(S_a), pts_a[inliers])
    full_b = apply_homography(np.linalg.inv(S_b), pts_b[inliers])
    # MAGSAC++'s model, refitted by geometric error on all its inliers: on a thin overlap its own fit
    # leaves the cross-track terms loose.
    H = refine_homography(np.linalg.inv(S_b) @ H_level @ S_a, full_a, full_b)
    spread, extent, overlap = spread_along(H, full_a, full_b, pyramid_a.full_size, pyramid_b.full_size)
    registration = CoarseRegistration(
        H, level, setting, spread, extent, overlap, full_a, full_b, spread >= min_spread, "", ()
    )
    return registration, len(pts_a)


def _failure(level: int, setting: HarrisSetting) -> CoarseRegistration:
    empty = np.zeros((0, 2))
    return CoarseRegistration(None, level, setting, 0.0, (0.0, 0.0), (0.0, 0.0), empty, empty, False, "", ())


def _match_level(
    image_a: Any,
    image_b: Any,
    setting: HarrisSetting,
    prior_level: np.ndarray | None,
    options: CoarseOptions,
    scale: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Mutual NCC matches of the corners of both level images, ``(M, 2)`` float64 level px in a (corners)
    and in b (sub-pixel NCC peaks near corners)."""
    xp = get_array_module(image_a)
    h = options.half_window
    corners = []
    for image in (image_a, image_b):
        found = harris_corners(
            image,
            radius=setting.radius,
            threshold=setting.threshold,
            k=HARRIS_K,
            window="gaussian",
            cell_px=options.cell_px,
            per_cell=options.per_cell,
        )
        desc, kept = window_descriptors(image, found.xy[: options.max_points], h)
        corners.append((found.xy[: options.max_points][kept], desc))
    (xy_a, desc_a), (xy_b, desc_b) = corners
    allowed = None
    if prior_level is not None:
        keep_a = xp.asarray(_inside(prior_level, to_host(xy_a), image_b.shape, h))
        keep_b = xp.asarray(_inside(np.linalg.inv(prior_level), to_host(xy_b), image_a.shape, h))
        xy_a, desc_a, xy_b, desc_b = xy_a[keep_a], desc_a[keep_a], xy_b[keep_b], desc_b[keep_b]
        predicted = xp.asarray(apply_homography(prior_level, to_host(xy_a)), dtype=xy_a.dtype)
        allowed = shift_window(predicted, xy_b, (0.0, 0.0), options.prior_radius_px * scale)
    matched = match_ncc(desc_a, desc_b, threshold=options.ncc_threshold, mutual=True, allowed=allowed)
    # Each match's point in b to the sub-pixel NCC peak around it: a level px is 2**level native px.
    r = h + SUBPIXEL_SEARCH
    centre = xy_b[matched.index_b].astype(xp.int64)
    inside = (centre[:, 0] >= r) & (centre[:, 1] >= r)
    inside &= (centre[:, 0] < image_b.shape[1] - r) & (centre[:, 1] < image_b.shape[0] - r)
    rows = xp.nonzero(inside)[0]
    offsets = xp.arange(-r, r + 1)
    search = image_b[
        centre[rows, 1][:, None, None] + offsets[:, None], centre[rows, 0][:, None, None] + offsets[None, :]
    ]
    shift, _, ok = ncc_peaks(desc_a[matched.index_a[rows]], search, h, SUBPIXEL_SEARCH, options.ncc_threshold)
    rows_host = to_host(rows)[ok]
    pts_a = to_host(xy_a[matched.index_a]).astype(np.float64)[rows_host]
    # Matches too near b's border for the search, or without a clear peak, are left out: kept at whole
    # level px, they would cost the model more accuracy than their number gives it.
    pts_b = to_host(centre).astype(np.float64)[rows_host] + shift[ok]
    return pts_a, pts_b


def _inside(H: np.ndarray, xy: np.ndarray, shape: tuple[int, ...], margin: float) -> np.ndarray:
    """``(N,) bool``: points that ``H`` maps at least ``margin`` px inside an image of ``shape``."""
    q = apply_homography(H, xy)
    return (q[:, 0] >= margin) & (q[:, 1] >= margin) & (q[:, 0] < shape[1] - margin) & (q[:, 1] < shape[0] - margin)
