"""Fine tie points of a strip frame pair at native resolution, as the source work does them: the predicted
overlap cut into blocks, the strongest Harris corner of each block, its NCC maximum searched a few px around
where the coarse homography predicts it (sub-pixel by a parabola through the peak on each axis), then a
fundamental-matrix RANSAC and a homography residual check. Only small windows of either frame are read.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from gpu_kernels.backend import Device, get_array_module, to_device, to_host
from gpu_kernels.harris import harris_response
from workers.algorithms.mosaic.alignment import apply_homography
from workers.algorithms.strips.coarse import HARRIS_K
from workers.algorithms.strips.homography import refine_homography
from workers.algorithms.strips.ncc_search import ncc_peaks, normalised_windows
from workers.algorithms.strips.overlap import long_axis, overlap_polygon
from workers.algorithms.strips.sources import GREEN, Windowed

COUNTS = ("corners", "inside", "peaks", "epipolar", "kept")  # PairTies.counts after "blocks", in step order


@dataclass(frozen=True)
class PairTies:
    """Tie points of frames ``frames[0]`` (a) and ``frames[1]`` (b).

    Attributes
    ----------
    frames : (a, b) frame indices, as given.
    points_a, points_b : (N, 2) float64, native pixel (x, y), matched rows; ``points_a`` are pixel centres.
    score : (N,) float32 NCC at the peak.
    counts : what each step kept: ``blocks``, ``corners`` (blocks with a corner), ``inside`` (predicted
        inside b), ``peaks`` (a usable NCC peak), ``epipolar`` (F-matrix inliers), ``kept``.
    """

    frames: tuple[int, int]
    points_a: np.ndarray
    points_b: np.ndarray
    score: np.ndarray
    counts: dict[str, int]


@dataclass(frozen=True)
class FineOptions:
    """Parameters of the native-resolution search."""

    half_window: int = 7  # NCC window half side, native px: (2 h + 1)^2 windows
    search_px: int = 8  # the NCC maximum is searched within +- this of the prediction, native px
    probe_px: int = 48  # side of the square read at each block's centre, in which its corner is taken
    harris_threshold: float = 1e-5  # a block whose strongest response is lower has no corner
    min_ncc: float = 0.8  # least NCC at the peak
    epipolar_px: float = 1.0  # F-matrix RANSAC threshold: distance to the epipolar line, px
    residual_px: float = 1.0  # homography residual check: largest transfer error kept, px
    channel: int = GREEN  # channel of colour windows used (BGR index)


def fine_tie_points(
    frame_a: Windowed,
    frame_b: Windowed,
    H_ab: np.ndarray,
    n_points: int = 400,
    frames: tuple[int, int] = (0, 1),
    options: FineOptions = FineOptions(),
    device: Device = "cpu",
) -> PairTies:
    """Tie points of frames a and b at native resolution, guided by the coarse homography ``H_ab``.

    The overlap that ``H_ab`` predicts (a polygon in a) is cut into about ``n_long x n_short`` blocks,
    ``n_long = round(sqrt(k N))`` along the overlap's long side and ``n_short = round(N / n_long)`` across,
    ``k`` the overlap's aspect (long / short) and ``N = n_points``, so blocks are about square (the source
    work's ``Ny = sqrt(k N)``, ``Nx = N / Ny``, with ``Ny`` counted along the long side). In each
    block a ``probe_px`` square is read and its strongest Harris response (k = 0.04, 3x3 Sobel, 3x3
    Gaussian window; ``gpu_kernels.harris``) is the block's point; its window is matched in b (see
    :func:`carry_ties`).

    Parameters
    ----------
    frame_a, frame_b : the frames, read by window (``WindowReader``, or arrays).
    H_ab : (3, 3) native a px -> native b px (:func:`register_coarse`).
    n_points : the number of blocks, i.e. of tie points wanted.
    frames : the pair's frame indices, carried into the result for :func:`build_tracks`.

    Returns
    -------
    PairTies, empty when the predicted overlap is too small for one window and its search.
    """
    if n_points < 1:
        raise ValueError(f"n_points must be positive, got {n_points}")
    o = options
    size_a, size_b = _size(frame_a), _size(frame_b)
    blocks = _blocks(overlap_polygon(H_ab, size_a, size_b), n_points, long_axis(size_a))
    side = min(o.probe_px, int(np.min(blocks[:, 2:] - blocks[:, :2]))) if len(blocks) else 0
    if side < 2 * o.half_window + 1:
        return _empty(frames, {"blocks": len(blocks), **dict.fromkeys(COUNTS, 0)})
    centres, templates = _block_corners(frame_a, blocks, side, o, device)
    ties = _search(frame_b, H_ab, centres, templates, frames, o, device)
    return PairTies(ties.frames, ties.points_a, ties.points_b, ties.score, {"blocks": len(blocks), **ties.counts})


def carry_ties(
    frame_a: Windowed,
    frame_c: Windowed,
    points_a: np.ndarray,
    H_ac: np.ndarray,
    frames: tuple[int, int] = (0, 2),
    options: FineOptions = FineOptions(),
    device: Device = "cpu",
) -> PairTies:
    """Carry given points of frame a into frame c: the window centred on each is searched by NCC within
    ``options.search_px`` of where ``H_ac`` predicts it, refined to sub-pixel and filtered (F matrix, then
    homography residual), as :func:`fine_tie_points` does for its block corners.

    Points found in pair (a, b) carried into c keep their exact position in a, so :func:`build_tracks`
    joins the two pairs' observations into tracks of three frames.

    Parameters
    ----------
    points_a : (N, 2) float pixel (x, y) in a, rounded to the nearest pixel centre.
    H_ac : (3, 3) native a px -> native c px.

    Returns
    -------
    PairTies
    """
    o = options
    h = o.half_window
    centres = np.rint(np.asarray(points_a, np.float64).reshape(-1, 2)).astype(np.int64)
    w, hgt = _size(frame_a)
    inside = (centres[:, 0] >= h) & (centres[:, 1] >= h) & (centres[:, 0] < w - h) & (centres[:, 1] < hgt - h)
    centres = centres[inside]
    windows = [_channel(frame_a[y - h : y + h + 1, x - h : x + h + 1], o.channel) for x, y in centres]
    stack = np.stack(windows) if windows else np.zeros((0, 2 * h + 1, 2 * h + 1), np.uint8)
    templates = normalised_windows(to_device(stack, device))
    return _search(frame_c, H_ac, centres, templates, frames, o, device)


@dataclass(frozen=True)
class TieFilter:
    """Result of :func:`filter_ties`: ``keep`` and ``epipolar`` (N,) bool (kept; F-matrix inliers), the
    fundamental matrix ``F`` and the homography ``H`` (3, 3) a px -> b px fitted to the kept points (None when
    too few points)."""

    keep: np.ndarray
    epipolar: np.ndarray
    F: np.ndarray | None
    H: np.ndarray | None


def filter_ties(
    points_a: np.ndarray, points_b: np.ndarray, epipolar_px: float = 1.0, residual_px: float = 1.0
) -> TieFilter:
    """Drop false tie points: a fundamental matrix by RANSAC (``cv2.findFundamentalMat``, ``FM_RANSAC``),
    then a homography fitted to its inliers (USAC MAGSAC++, then :func:`refine_homography` on the points it
    explains) whose transfer error must stay within ``residual_px``.

    The F matrix is the source work's filter and holds for any scene; it cannot see an error along the
    epipolar line, and for a scene this flat (7-10 km flying height) the epipolar geometry is nearly
    degenerate, so the homography check catches what it leaves.

    Parameters
    ----------
    points_a, points_b : (N, 2) float pixel (x, y), matched rows.

    Returns
    -------
    TieFilter; with fewer than 8 points nothing is kept.
    """
    a, b = np.asarray(points_a, np.float64), np.asarray(points_b, np.float64)
    n = len(a)
    none = np.zeros(n, bool)
    if n < 8:
        return TieFilter(none, none, None, None)
    cv2.setRNGSeed(n)  # same points, same answer
    F, mask = cv2.findFundamentalMat(a, b, cv2.FM_RANSAC, epipolar_px, 0.999, 5000)
    if F is None or mask is None or F.shape != (3, 3):
        return TieFilter(none, none, None, None)
    epipolar = mask.ravel().astype(bool)
    if epipolar.sum() < 8:
        return TieFilter(none, epipolar, F, None)
    H, hmask = cv2.findHomography(
        a[epipolar], b[epipolar], cv2.USAC_MAGSAC, residual_px, maxIters=5000, confidence=0.999
    )
    if H is None or hmask is None:
        return TieFilter(none, epipolar, F, None)
    keep = np.zeros(n, bool)
    keep[np.flatnonzero(epipolar)[hmask.ravel().astype(bool)]] = True
    # A few rounds of the model refitted to the points it explains and the points re-classified (the local
    # optimisation of LO-RANSAC), by geometric error: on an overlap 40 times longer than wide, the DLT's
    # algebraic least squares leaves px of error where the points fit to a tenth of one.
    for _ in range(2):
        if keep.sum() < 8:
            break
        H = refine_homography(H, a[keep], b[keep])
        keep = epipolar & (np.linalg.norm(apply_homography(H, a) - b, axis=1) <= residual_px)
    return TieFilter(keep, epipolar, F, H)


def _size(frame: Windowed) -> tuple[int, int]:
    return int(frame.shape[1]), int(frame.shape[0])


def _channel(window: np.ndarray, channel: int) -> np.ndarray:
    return window[..., channel] if window.ndim == 3 else window


def _empty(frames: tuple[int, int], counts: dict[str, int]) -> PairTies:
    return PairTies(frames, np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0, np.float32), counts)


def _blocks(polygon: np.ndarray, n: int, axis: int) -> np.ndarray:
    """``(M, 4) float64`` blocks ``(x0, y0, x1, y1)``, about square, ``M`` about ``n``, of the overlap
    ``polygon`` (K, 2) px.

    The overlap of two strip frames is a long parallelogram, a little slanted by the heading difference; its
    bounding box is tiled with blocks sized as if ``n`` of them tiled the polygon itself (long side = polygon
    extent, short side = its area / that extent), and the blocks whose centre lies in the polygon are kept.
    """
    if len(polygon) < 3:
        return np.zeros((0, 4))
    contour = polygon.astype(np.float32).reshape(-1, 1, 2)
    long_side = float(np.ptp(polygon[:, axis]))
    short_side = cv2.contourArea(contour) / max(long_side, 1e-9)
    if short_side <= 0:
        return np.zeros((0, 4))
    n_long = max(1, min(n, round(math.sqrt(long_side / short_side * n))))
    n_short = max(1, round(n / n_long))
    block = np.array([long_side / n_long, short_side / n_short])
    if axis == 1:
        block = block[::-1]
    lo, hi = polygon.min(axis=0), polygon.max(axis=0)
    count = np.maximum(1, np.rint((hi - lo) / block)).astype(np.int64)
    xs, ys = np.linspace(lo[0], hi[0], count[0] + 1), np.linspace(lo[1], hi[1], count[1] + 1)
    grid_x, grid_y = np.meshgrid(np.arange(count[0]), np.arange(count[1]))
    gx, gy = grid_x.ravel(), grid_y.ravel()
    boxes = np.column_stack([xs[gx], ys[gy], xs[gx + 1], ys[gy + 1]])
    centres = (boxes[:, :2] + boxes[:, 2:]) / 2
    inside = [cv2.pointPolygonTest(contour, (float(x), float(y)), False) >= 0 for x, y in centres]
    return boxes[np.asarray(inside, bool)]


def _block_corners(
    frame: Windowed, blocks: np.ndarray, side: int, o: FineOptions, device: Device
) -> tuple[np.ndarray, Any]:
    """The strongest Harris corner of a ``side`` square at each block's centre: ``(n, 2) int64`` native px,
    and the ``(n, (2h+1)^2) float32`` normalised windows centred on them (on ``device``); blocks whose
    strongest response is below the threshold give none."""
    w, h = _size(frame)
    c0 = np.clip(np.rint((blocks[:, 0] + blocks[:, 2]) / 2).astype(np.int64) - side // 2, 0, w - side)
    r0 = np.clip(np.rint((blocks[:, 1] + blocks[:, 3]) / 2).astype(np.int64) - side // 2, 0, h - side)
    reads = [_channel(frame[r : r + side, c : c + side], o.channel) for c, r in zip(c0, r0, strict=True)]
    probes = to_device(np.stack(reads), device)
    xp = get_array_module(probes)
    n = len(probes)
    # All probes side by side in one image: one response call (one kernel launch on a GPU). A pixel's
    # response reads 2 px around it, so away from a probe's edge it is the probe's own.
    strip = probes.transpose(1, 0, 2).reshape(side, n * side)
    response = harris_response(strip, k=HARRIS_K, window="gaussian", scale=1.0 / 255.0)
    response = response.reshape(side, n, side).transpose(1, 0, 2)
    m = max(o.half_window, 2)
    interior = response[:, m : side - m, m : side - m].reshape(n, -1)
    best = interior.argmax(axis=1)
    strong = interior[xp.arange(n), best] > o.harris_threshold
    iy, ix = best // (side - 2 * m) + m, best % (side - 2 * m) + m
    t = xp.arange(-o.half_window, o.half_window + 1)
    windows = probes[xp.arange(n)[:, None, None], iy[:, None, None] + t[:, None], ix[:, None, None] + t]
    keep = to_host(strong)
    centres = np.column_stack([c0 + to_host(ix), r0 + to_host(iy)])[keep]
    return centres, normalised_windows(windows[strong])


def _search(
    frame_b: Windowed,
    H_ab: np.ndarray,
    centres: np.ndarray,
    templates: Any,
    frames: tuple[int, int],
    o: FineOptions,
    device: Device,
) -> PairTies:
    """NCC search of each template of a (centred on ``centres``) around its prediction in b, sub-pixel
    peak, then :func:`filter_ties`."""
    h, s = o.half_window, o.search_px
    r = h + s
    w, hgt = _size(frame_b)
    counts = {"corners": len(centres)}
    if len(centres) == 0:
        return _empty(frames, {**dict.fromkeys(COUNTS, 0), **counts})
    centre_b = np.rint(apply_homography(H_ab, centres)).astype(np.int64)
    inside = (centre_b[:, 0] >= r) & (centre_b[:, 1] >= r) & (centre_b[:, 0] < w - r) & (centre_b[:, 1] < hgt - r)
    counts["inside"] = int(inside.sum())
    centres, centre_b = centres[inside], centre_b[inside]
    if len(centres) == 0:
        return _empty(frames, {**dict.fromkeys(COUNTS, 0), **counts})
    search = to_device(
        np.stack([_channel(frame_b[y - r : y + r + 1, x - r : x + r + 1], o.channel) for x, y in centre_b]), device
    )
    templates = templates[to_device(inside, device)]
    offset, score, ok = ncc_peaks(templates, search, h, s, o.min_ncc)
    points_a = centres[ok].astype(np.float64)
    points_b = centre_b[ok] + offset[ok]
    counts["peaks"] = int(ok.sum())
    kept = filter_ties(points_a, points_b, o.epipolar_px, o.residual_px)
    counts["epipolar"], counts["kept"] = int(kept.epipolar.sum()), int(kept.keep.sum())
    keep = kept.keep
    return PairTies(frames, points_a[keep], points_b[keep], score[ok][keep], counts)
