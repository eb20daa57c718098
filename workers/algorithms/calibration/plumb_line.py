"""Distortion alone from images of straight lines (Brown 1971, "Close-range camera calibration"),
independent of any target geometry."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from workers.algorithms.calibration.solver import covariance, free_distortion_terms, solve_lm, split_by_counts
from workers.algorithms.geometry import Camera


@dataclass(frozen=True, eq=False)
class PlumbLineResult:
    """Distortion fitted to straight lines.

    Attributes
    ----------
    camera : the input camera with the fitted terms (same convention and intrinsics).
    line_rms_px : (L,) float64 RMS distance of each line's corrected points to its fitted line.
    rms_px : overall RMS over all points.
    residuals : per line, (N_l,) float64 signed distances, px.
    std : term -> standard deviation.
    """

    camera: Camera
    line_rms_px: np.ndarray
    rms_px: float
    residuals: list[np.ndarray]
    std: dict[str, float]


def plumb_line(
    lines: Sequence[np.ndarray], camera: Camera, terms: Sequence[str] = ("k1", "k2", "t1", "t2")
) -> PlumbLineResult:
    """Distortion terms that make images of straight lines straight (Brown 1971's plumb-line method).

    Each point is corrected to ideal coordinates with the trial terms (``Camera.pixel_to_normalised``,
    scaled back to pixels by fx, fy), every line gets its total-least-squares straight line, and LM
    minimises the perpendicular distances. The intrinsics of ``camera`` only normalise and are not
    estimated: the distortion centre is the principal point. Distances are in ideal (corrected) pixels.

    Parameters
    ----------
    lines : sequence of (N_l, 2) float64 pixel (x, y) points along one straight line each; at least 3
        points per line and 2 lines, spread over the frame to constrain the outer field.
    camera : starting camera; its fixed terms keep their values.
    terms : the distortion terms to estimate, from k1, k2, k3, t1, t2.

    Returns
    -------
    PlumbLineResult
    """
    free = free_distortion_terms(terms, camera.convention)
    pts, line_id, counts = _as_lines(lines)
    if not free or len(pts) - 2 * len(counts) < len(free):
        raise ValueError("plumb_line needs at least one term and more points beyond 2 per line than terms")

    def residuals(x: np.ndarray) -> np.ndarray:
        trial = camera.replace(**dict(zip(free, map(float, x), strict=True)))
        ideal = trial.pixel_to_normalised(pts) * [camera.fx, camera.fy]
        return _line_distances(ideal, line_id, len(counts))

    x0 = np.array([getattr(camera, t) for t in free])
    x, res, jac = solve_lm(residuals, x0, len(free), np.zeros(len(pts), dtype=int))
    std = np.sqrt(np.diag(covariance(jac, res)))
    per_line = split_by_counts(res, counts)
    return PlumbLineResult(
        camera=camera.replace(**dict(zip(free, map(float, x), strict=True))),
        line_rms_px=np.array([np.sqrt(np.mean(r**2)) for r in per_line]),
        rms_px=float(np.sqrt(np.mean(res**2))),
        residuals=per_line,
        std=dict(zip(free, map(float, std), strict=True)),
    )


def _as_lines(lines: Sequence[np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Stacked points (N, 2), their line index (N,) and points per line (L,)."""
    if len(lines) < 2:
        raise ValueError(f"plumb_line needs at least 2 lines, got {len(lines)}")
    arrays = [np.asarray(line, dtype=np.float64) for line in lines]
    for index, a in enumerate(arrays):
        if a.ndim != 2 or a.shape[1] != 2 or len(a) < 3 or not np.all(np.isfinite(a)):
            raise ValueError(f"line {index} must be finite (N, 2) pixel points with N >= 3, got {a.shape}")
    counts = np.array([len(a) for a in arrays])
    return np.concatenate(arrays), np.repeat(np.arange(len(arrays)), counts), counts


def _line_distances(pts: np.ndarray, line_id: np.ndarray, n_lines: int) -> np.ndarray:
    """Signed distance of every point to its line's total-least-squares line, (N, 2) -> (N,)."""
    count = np.bincount(line_id, minlength=n_lines)
    mean = np.stack([np.bincount(line_id, pts[:, k], n_lines) / count for k in (0, 1)], axis=1)
    d = pts - mean[line_id]
    sxx, syy, sxy = (np.bincount(line_id, w, n_lines) for w in (d[:, 0] ** 2, d[:, 1] ** 2, d[:, 0] * d[:, 1]))
    theta = 0.5 * np.arctan2(2.0 * sxy, sxx - syy)  # direction of largest spread (the line)
    normal = np.stack([-np.sin(theta), np.cos(theta)], axis=1)
    # theta wraps at +-90 degrees (a vertical line), which would flip the sign of a whole line's
    # distances between two evaluations: orient each normal by its line's first-to-last direction.
    ends = np.cumsum(count) - 1  # lines are contiguous runs of points (``_as_lines``)
    chord = pts[ends] - pts[ends - count + 1]
    side = np.sign(normal[:, 0] * -chord[:, 1] + normal[:, 1] * chord[:, 0])
    normal *= np.where(side == 0, 1.0, side)[:, None]
    return np.sum(d * normal[line_id], axis=1)
