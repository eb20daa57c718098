"""Tie points found on reduced registration copies, refined on the working copies by normalised
cross-correlation (the sub-pixel NCC refinement of area-based matching: OpenCV ``cv2.matchTemplate``'s
``TM_CCOEFF_NORMED``, here batched over many points, peak located by a parabola through its neighbours on
each axis)."""

from __future__ import annotations

import cv2
import numpy as np

from workers.algorithms.mosaic.alignment import apply_homography, frame_corners
from workers.algorithms.mosaic.homography import estimate_homography, spread_subset


def refine_tie_points(
    gray_i: np.ndarray,
    gray_j: np.ndarray,
    points_i: np.ndarray,
    points_j: np.ndarray,
    H_ij: np.ndarray,
    half_window: int = 7,
    search_px: int = 3,
    min_ncc: float = 0.8,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Move each tie point of frame i to its nearest pixel centre and find its partner in frame j by NCC.

    Frame j is resampled onto frame i's pixel grid around each point through the pair's homography, so
    the template and the search window differ only by the residual shift the correlation measures.

    Parameters
    ----------
    gray_i, gray_j : (H, W) uint8 working copies of the two frames.
    points_i, points_j : (N, 2) float pixel (x, y) tie points, ``points_j ~ H_ij points_i``.
    H_ij : (3, 3) frame i px -> frame j px.
    half_window : the template is ``2 h + 1`` px square.
    search_px : largest shift searched, px on frame i's grid.
    min_ncc : a point whose best correlation is lower keeps its given position.

    Returns
    -------
    points_i, points_j : (N, 2) float64, refined where ``refined`` is True and as given elsewhere.
    refined : (N,) bool
    """
    if gray_i.ndim != 2 or gray_j.ndim != 2:
        raise ValueError("refine_tie_points expects (H, W) grey images")
    out_i = np.asarray(points_i, np.float64).copy()
    out_j = np.asarray(points_j, np.float64).copy()
    refined = np.zeros(len(out_i), bool)
    h, s = half_window, search_px
    height, width = gray_i.shape
    centres = np.rint(out_i).astype(np.int64)
    inside = (centres[:, 0] >= h) & (centres[:, 1] >= h) & (centres[:, 0] < width - h) & (centres[:, 1] < height - h)
    # a chunk of points at once (one remap and a few array operations rather than a warp and a correlation
    # per point, which cost ~10x as much in calls); chunks bound the patches held to well under a MiB
    todo = np.flatnonzero(inside)
    for chunk in np.array_split(todo, max(1, -(-len(todo) // REFINE_CHUNK))):
        shift, ok = _ncc_shifts(gray_i, gray_j, centres[chunk], H_ij, h, s, min_ncc)
        done = chunk[ok]
        out_i[done] = centres[done]
        out_j[done] = apply_homography(H_ij, centres[done] + shift[ok])
        refined[done] = True
    return out_i, out_j, refined


REFINE_CHUNK = 256  # refine_tie_points: points correlated in one batch


def overlap_share(H_ij: np.ndarray, size_i: tuple[int, int], size_j: tuple[int, int]) -> float:
    """Share (0..1) of frame i's area that ``H_ij`` (frame i px -> frame j px) maps inside frame j; 0 for a
    model that folds the frame or sends part of it behind the camera."""
    corners = frame_corners(*size_i)
    q = corners @ H_ij[:, :2].T + H_ij[:, 2]
    if np.any(q[:, 2] <= 1e-12):
        return 0.0
    quad = (q[:, :2] / q[:, 2:3]).astype(np.float32)
    if cv2.contourArea(quad, oriented=True) <= 0:  # clockwise on screen (y down) is positive: else folded
        return 0.0
    area, _ = cv2.intersectConvexConvex(quad, frame_corners(*size_j).astype(np.float32))
    inside_j = float(area)
    # back to frame i's pixels through the local scale of the map (area ratio of the quad to the frame)
    return min(1.0, inside_j / cv2.contourArea(quad))


def tie_corners(gray: np.ndarray, count: int = 4000) -> np.ndarray:
    """(N <= count, 2) float32 pixel (x, y): Shi-Tomasi corners of a (H, W) uint8 working copy, spread over it
    by a minimum distance (``cv2.goodFeaturesToTrack``), where :func:`guided_tie_points` correlates."""
    spacing = max(3.0, 0.7 * float(np.sqrt(gray.size / max(count, 1))))
    found = cv2.goodFeaturesToTrack(gray, count, 0.005, spacing, blockSize=5)
    return np.zeros((0, 2), np.float32) if found is None else found.reshape(-1, 2).astype(np.float32)


def guided_tie_points(
    gray_i: np.ndarray,
    gray_j: np.ndarray,
    corners_i: np.ndarray,
    H_ij: np.ndarray,
    max_points: int,
    search_px: int,
    fine_px: int = 4,
    half_window: int = 7,
    min_ncc: float = 0.95,
) -> tuple[np.ndarray, np.ndarray]:
    """Tie points of a pair found by correlation where a homography says the frames overlap (guided
    matching, as COLMAP's and the area-based matching of aerial triangulation): spread over the whole
    overlap, whatever part of it the features that found the homography came from.

    Of frame i's ``corners_i`` (:func:`tie_corners`), those the prediction places inside frame j are thinned
    to ``max_points`` spread over the overlap (:func:`~workers.algorithms.mosaic.spread_subset`) and
    correlated with frame j resampled through ``H_ij`` within ``search_px`` (:func:`refine_tie_points`).
    A search wider than ``fine_px`` is done twice: the second about the homography fitted (USAC) to the
    first, within ``fine_px``, since a sub-pixel peak is least biased where the resampled window already
    lies on its partner (planted homography, prediction 6 px off: median error 0.15 px after one pass).

    Parameters
    ----------
    gray_i, gray_j : (H, W) uint8 working copies.
    corners_i : (N, 2) float pixel (x, y) in frame i.
    H_ij : (3, 3) predicted frame i px -> frame j px: the pair's own model, or one chained through others.
    max_points : most corners correlated.
    search_px : largest error of the prediction searched, px.
    min_ncc : lowest correlation kept; high, because a planar homography's resampling only matches where the
        scene is that plane (trees and cars correlate worse).

    Returns
    -------
    points_i, points_j : (M, 2) float64 pixel (x, y), the points whose correlation peak was found.
    """
    margin = half_window + search_px + 1
    inner = np.array(gray_j.shape[::-1], np.float64) - 1 - margin
    predicted = apply_homography(H_ij, corners_i)
    inside = np.all((predicted >= margin) & (predicted <= inner), axis=1)
    candidates = np.asarray(corners_i, np.float64)[inside]
    if not len(candidates):
        return np.zeros((0, 2)), np.zeros((0, 2))
    points_i = candidates[spread_subset(candidates, (gray_i.shape[1], gray_i.shape[0]), max_points)]
    found_i, found_j, refined = refine_tie_points(
        gray_i, gray_j, points_i, apply_homography(H_ij, points_i), H_ij, half_window, search_px, min_ncc
    )
    if search_px > fine_px and refined.sum() >= 8:
        fitted, _ = estimate_homography(found_i[refined], found_j[refined], 1.0)
        if fitted is not None:
            found_i, found_j, refined = refine_tie_points(
                gray_i, gray_j, points_i, apply_homography(fitted, points_i), fitted, half_window, fine_px, min_ncc
            )
    return found_i[refined], found_j[refined]


def refined_pair_ties(
    gray_i: np.ndarray,
    gray_j: np.ndarray,
    ties_i: np.ndarray,
    ties_j: np.ndarray,
    H_ij: np.ndarray,
    threshold_px: float,
    min_inliers: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A pair's (N, 2) descriptor tie points refined on the working copies (:func:`refine_tie_points`), and the
    (N,) bool of those to keep: within ``threshold_px`` of the model re-fitted on the refined points (USAC judged
    the coarser positions) and refined, where at least ``min_inliers`` are (the rest are that coarse)."""
    ties_i, ties_j, refined = refine_tie_points(gray_i, gray_j, ties_i, ties_j, H_ij)
    _, close = refit_homography(ties_i, ties_j, H_ij, threshold_px)
    if (close & refined).sum() >= min_inliers:
        close &= refined
    return ties_i, ties_j, close


def refit_homography(
    points_i: np.ndarray, points_j: np.ndarray, H_ij: np.ndarray, threshold_px: float, rounds: int = 3
) -> tuple[np.ndarray, np.ndarray]:
    """The pair's homography re-fitted by least squares on the tie points it explains within ``threshold_px``,
    a few rounds (the local optimisation of LO-RANSAC, Chum et al. 2003), once the points are refined to a
    precision the robust fit on registration copies never saw.

    Parameters
    ----------
    points_i, points_j : (N, 2) float pixel (x, y) tie points, ``points_j ~ H_ij points_i``.
    H_ij : (3, 3) the starting model, frame i px -> frame j px.

    Returns
    -------
    H : (3, 3) float64, H[2, 2] = 1 (``H_ij`` itself where a fit fails or too few points are close)
    close : (N,) bool, the points within ``threshold_px`` of it
    """
    H = np.asarray(H_ij, np.float64)
    close = np.linalg.norm(apply_homography(H, points_i) - points_j, axis=1) <= threshold_px
    for _ in range(rounds):
        if close.sum() < 8:
            break
        fit, _ = cv2.findHomography(points_i[close].astype(np.float64), points_j[close].astype(np.float64), 0)
        if fit is None or abs(fit[2, 2]) < 1e-12:
            break
        H = fit / fit[2, 2]
        close = np.linalg.norm(apply_homography(H, points_i) - points_j, axis=1) <= threshold_px
    return H, close


def _ncc_shifts(
    gray_i: np.ndarray, gray_j: np.ndarray, centres: np.ndarray, H_ij: np.ndarray, h: int, s: int, min_ncc: float
) -> tuple[np.ndarray, np.ndarray]:
    """(n, 2) float64 sub-pixel shift (x, y) of the NCC peak of each template of frame i, centred on the
    (n, 2) int pixel ``centres``, in frame j resampled onto frame i's grid; and (n,) bool where it is usable.

    The peak is the first maximum (as ``cv2.minMaxLoc``); unusable on a flat template, below ``min_ncc``
    or on the edge of the search, where no parabola can be fitted.
    """
    n, m = len(centres), 2 * s + 1
    if n == 0:
        return np.zeros((0, 2)), np.zeros(0, bool)
    offsets = np.arange(-h, h + 1)
    template = gray_i[centres[:, 1, None, None] + offsets[:, None], centres[:, 0, None, None] + offsets]
    score, flat = _ncc_scores(_search_patches(gray_j, centres, H_ij, h + s), template.astype(np.float64))
    best = np.argmax(score.reshape(n, -1), axis=1)
    py, px = np.divmod(best, m)
    k = np.arange(n)
    peak = score[k, py, px]
    ok = ~flat & (peak >= min_ncc) & (px > 0) & (px < 2 * s) & (py > 0) & (py < 2 * s)
    pxc, pyc = np.clip(px, 1, 2 * s - 1), np.clip(py, 1, 2 * s - 1)  # where not ok, any valid neighbour
    dx = px - s + _parabola_peak(score[k, pyc, pxc - 1], peak, score[k, pyc, pxc + 1])
    dy = py - s + _parabola_peak(score[k, pyc - 1, pxc], peak, score[k, pyc + 1, pxc])
    return np.column_stack([dx, dy]), ok


def _search_patches(gray_j: np.ndarray, centres: np.ndarray, H_ij: np.ndarray, r: int) -> np.ndarray:
    """(n, 2r+1, 2r+1) float64: frame j resampled (bilinear, 0 outside) on frame i's pixels within ``r`` of
    each of the (n, 2) int ``centres``, through ``H_ij``; what ``cv2.warpPerspective`` gives per point, in
    one ``cv2.remap``."""
    n, side = len(centres), 2 * r + 1
    grid = np.arange(-r, r + 1, dtype=np.float64)
    xi = centres[:, 0, None, None] + grid[None, None, :]
    yi = centres[:, 1, None, None] + grid[None, :, None]
    w = H_ij[2, 0] * xi + H_ij[2, 1] * yi + H_ij[2, 2]
    map_x = ((H_ij[0, 0] * xi + H_ij[0, 1] * yi + H_ij[0, 2]) / w).astype(np.float32)
    map_y = ((H_ij[1, 0] * xi + H_ij[1, 1] * yi + H_ij[1, 2]) / w).astype(np.float32)
    flat_x, flat_y = map_x.reshape(n * side, side), map_y.reshape(n * side, side)
    patches = cv2.remap(gray_j, flat_x, flat_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
    return patches.reshape(n, side, side).astype(np.float64)


def _ncc_scores(search: np.ndarray, template: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``cv2.matchTemplate(..., TM_CCOEFF_NORMED)`` of each (n, t, t) template over its (n, S, S) search
    patch, batched: (n, S - t + 1, S - t + 1) float64 scores (0 over a flat window), and (n,) bool where the
    template is flat (standard deviation under 2 grey levels: its correlation peak would be noise)."""
    t = template.shape[1]
    zero_mean = template - template.mean(axis=(1, 2), keepdims=True)
    t_norm2 = (zero_mean**2).sum(axis=(1, 2))
    # the windows' sums by box filters; their products with the zero-mean template by cv2.matchTemplate's
    # plain correlation, point by point (twice the speed of one einsum over strided views of every window)
    w_sum, w_sum2 = _box_sums(search, t)
    w_var = np.maximum(w_sum2 - w_sum**2 / (t * t), 0.0)
    patches, kernels = search.astype(np.float32), zero_mean.astype(np.float32)
    numer = np.stack([cv2.matchTemplate(patches[k], kernels[k], cv2.TM_CCORR) for k in range(len(search))])
    denom = np.sqrt(w_var * t_norm2[:, None, None])
    score = np.where(denom > 0, numer / np.where(denom > 0, denom, 1.0), 0.0)
    return score, t_norm2 < 4.0 * t * t


def _box_sums(images: np.ndarray, t: int) -> tuple[np.ndarray, np.ndarray]:
    """(n, H, W) float64 -> the sum and the sum of squares over every t x t window of each image, both
    (n, H - t + 1, W - t + 1)."""
    n, height, width = images.shape
    tall = images.reshape(n * height, width)  # a box inside one image never reads its neighbours
    sums = [f(tall, cv2.CV_64F, (t, t), normalize=False).reshape(n, height, width) for f in _BOX_FILTERS]
    r = t // 2
    return sums[0][:, r : height - r, r : width - r], sums[1][:, r : height - r, r : width - r]


_BOX_FILTERS = (cv2.boxFilter, cv2.sqrBoxFilter)


def _parabola_peak(left: np.ndarray, centre: np.ndarray, right: np.ndarray) -> np.ndarray:
    """Offsets (-0.5 .. 0.5) of the vertices of the parabolas through three samples one apart, elementwise;
    0 where they do not open downwards."""
    den = left - 2.0 * centre + right
    safe = np.where(den < 0, den, -1.0)
    return np.where(den < 0, np.clip(0.5 * (left - right) / safe, -0.5, 0.5), 0.0)
