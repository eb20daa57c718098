"""Tie points found on reduced registration copies, refined on the working copies by normalised
cross-correlation (the sub-pixel NCC refinement of area-based matching; OpenCV ``cv2.matchTemplate`` with
``TM_CCOEFF_NORMED``, peak located by a parabola through its neighbours on each axis)."""

from __future__ import annotations

import cv2
import numpy as np

from workers.algorithms.mosaic.alignment import apply_homography


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
    side = 2 * (h + s) + 1
    height, width = gray_i.shape
    centres = np.rint(out_i).astype(int)
    inside = (centres[:, 0] >= h) & (centres[:, 1] >= h) & (centres[:, 0] < width - h) & (centres[:, 1] < height - h)
    flags = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
    for k in np.flatnonzero(inside):
        cx, cy = centres[k]
        template = gray_i[cy - h : cy + h + 1, cx - h : cx + h + 1]
        if template.std() < 2.0:  # flat: the correlation peak would be noise
            continue
        # search pixel (u, v) -> frame i pixel (cx - h - s + u, cy - h - s + v) -> frame j
        origin = np.array([[1.0, 0.0, cx - h - s], [0.0, 1.0, cy - h - s], [0.0, 0.0, 1.0]])
        search = cv2.warpPerspective(gray_j, H_ij @ origin, (side, side), flags=flags, borderMode=cv2.BORDER_CONSTANT)
        score = cv2.matchTemplate(search, template, cv2.TM_CCOEFF_NORMED)
        _, best, _, (px, py) = cv2.minMaxLoc(score)
        if best < min_ncc or not (0 < px < 2 * s and 0 < py < 2 * s):
            continue  # weak, or on the edge of the search: no sub-pixel peak to fit
        dx = px - s + _parabola_peak(score[py, px - 1], score[py, px], score[py, px + 1])
        dy = py - s + _parabola_peak(score[py - 1, px], score[py, px], score[py + 1, px])
        out_i[k] = (cx, cy)
        out_j[k] = apply_homography(H_ij, np.array([[cx + dx, cy + dy]]))[0]
        refined[k] = True
    return out_i, out_j, refined


def _parabola_peak(left: float, centre: float, right: float) -> float:
    """Offset (-0.5 .. 0.5) of the vertex of the parabola through three samples one apart."""
    den = left - 2.0 * centre + right
    return 0.0 if den >= 0 else float(np.clip(0.5 * (left - right) / den, -0.5, 0.5))
