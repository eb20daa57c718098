"""Crack geometry on a boolean crack mask at a known scale: skeleton, per-crack polylines, length, width,
orientation, totals, and matching of cracks between load steps.

Coordinates: pixel (col, row) has its centre at x = col * mm_per_px, y = row * mm_per_px (mm, y down, as
in the raster). Orientations are in degrees counter-clockwise from the +x axis as seen on the image
(y up), folded into [0, 180).

The chain: a strictly 8-thin skeleton (:mod:`workers.algorithms.cracks.skeleton`), branches between
junctions traced into ordered paths, spurs shorter than the local width pruned (as in skan, Nunez-Iglesias
et al. 2018), lengths along Gaussian-smoothed paths, widths as mask area per unit length along the path.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import cv2
import numpy as np
from scipy import ndimage as ndi
from scipy.spatial import cKDTree

from workers.algorithms.cracks.skeleton import EIGHT_CONNECTED, RING, neighbour_count, thin

DEFAULT_LENGTH_BINS_MM = (0.0, 1.0, 2.0, 5.0, 10.0, 20.0, 50.0, 100.0, 200.0, 500.0, np.inf)


@dataclass(frozen=True)
class Crack:
    """One crack: an 8-connected component of the mask, measured along its skeleton."""

    paths_mm: tuple[np.ndarray, ...]  # per branch, (N, 2) float64 (x, y) mm, ordered, smoothed; junctions shared
    length_mm: float  # sum of the branch lengths
    mean_width_mm: float
    max_width_mm: float
    orientation_deg: float  # principal axis of the skeleton, [0, 180), counter-clockwise from +x with y up
    endpoints_mm: np.ndarray  # (K, 2) float64 (x, y) mm, the free ends of the skeleton
    bbox_mm: tuple[float, float, float, float]  # x_min, y_min, x_max, y_max of the crack's pixel centres
    # the photos' sampling across the crack where it is, mm per photo pixel (None: not known)
    photo_mm_per_px: float | None = None


@dataclass(frozen=True)
class CrackSummary:
    """Totals over the cracks of one image."""

    count: int
    total_length_mm: float
    mean_width_mm: float  # length-weighted
    max_width_mm: float
    histogram_edges_mm: np.ndarray  # (B + 1,) float64
    histogram_counts: np.ndarray  # (B,) int64, cracks per length bin


@dataclass(frozen=True)
class CrackMatch:
    """How one crack of the current stage relates to the previous stage."""

    current: int  # index into the current cracks
    status: Literal["new", "grown", "unchanged"]
    growth_mm: float  # length gained since the previous stage (the whole length for a new crack)
    previous: tuple[int, ...]  # indices of the previous cracks it continues


def _order_branch(pixels: set[tuple[int, int]]) -> list[tuple[int, int]]:
    """The pixels of one branch (a path or a loop, 8-connected) in walking order, (row, col)."""

    def neighbours(p: tuple[int, int]) -> list[tuple[int, int]]:
        return [(p[0] + dr, p[1] + dc) for dr, dc in RING if (p[0] + dr, p[1] + dc) in pixels]

    ends = [p for p in pixels if len(neighbours(p)) <= 1]
    start = min(ends) if ends else min(pixels)  # a loop starts anywhere
    path, seen = [start], {start}
    while True:
        step = [q for q in neighbours(path[-1]) if q not in seen]
        if not step:
            return path
        # 4-neighbours first: on a thin path a diagonal step past one would skip a pixel
        nxt = min(step, key=lambda q: abs(q[0] - path[-1][0]) + abs(q[1] - path[-1][1]))
        path.append(nxt)
        seen.add(nxt)


@dataclass
class _Branch:
    """A skeleton path between ends and/or junctions, in pixel (row, col) coordinates."""

    pixels: np.ndarray  # (N, 2) int64 ordered skeleton pixels
    junctions: tuple[int, int]  # junction cluster at the start / end (0: none)
    free: tuple[bool, bool]  # the start / end is a free end of the skeleton
    closed: bool = False  # a loop with no junction


def _branches(skeleton: np.ndarray) -> tuple[list[_Branch], np.ndarray, np.ndarray]:
    """Split a thin skeleton at its junctions.

    Returns
    -------
    branches : ordered paths between junction clusters and free ends.
    junction_labels : (H, W) int32, 8-connected clusters of pixels with >= 3 neighbours, 1..J (0 elsewhere).
    junction_centres : (J + 1, 2) float64 (row, col) centroid of each cluster (row 0 unused).
    """
    degree = neighbour_count(skeleton)
    junction_labels, n_junctions = ndi.label(skeleton & (degree >= 3), structure=EIGHT_CONNECTED)
    centres = np.zeros((n_junctions + 1, 2))
    if n_junctions:
        centres[1:] = ndi.center_of_mass(np.ones_like(skeleton), junction_labels, range(1, n_junctions + 1))
    padded = np.pad(junction_labels, 1)
    branch_labels, n_branches = ndi.label(skeleton & (degree < 3), structure=EIGHT_CONNECTED)
    branches = []
    for index, box in enumerate(ndi.find_objects(branch_labels), start=1):
        rows, cols = np.nonzero(branch_labels[box] == index)
        pixels = {(int(r) + box[0].start, int(c) + box[1].start) for r, c in zip(rows, cols, strict=True)}
        path = np.array(_order_branch(pixels), dtype=np.int64)
        at_start = np.unique(padded[path[0, 0] : path[0, 0] + 3, path[0, 1] : path[0, 1] + 3])[1:].tolist()
        at_end = np.unique(padded[path[-1, 0] : path[-1, 0] + 3, path[-1, 1] : path[-1, 1] + 3])[1:].tolist()
        if len(path) == 1:  # one pixel between two junctions, or a one-pixel spur
            at_end = at_start[1:]
        ends = [at_start[0] if at_start else 0, at_end[-1] if at_end else 0]
        loop = len(path) > 2 and max(abs(path[0] - path[-1])) <= 1 and ends == [0, 0]
        free = tuple(j == 0 and degree[r, c] <= 1 for j, (r, c) in zip(ends, (path[0], path[-1]), strict=True))
        branches.append(_Branch(path, (ends[0], ends[1]), (bool(free[0]), bool(free[1])), bool(loop)))
    return branches, junction_labels, centres


def _points(branch: _Branch, centres: np.ndarray) -> np.ndarray:
    """(M, 2) float64 (row, col): the branch pixels with the centres of the junctions it ends on."""
    parts = [centres[branch.junctions[0]][None]] if branch.junctions[0] else []
    parts.append(branch.pixels.astype(np.float64))
    if branch.junctions[1]:
        parts.append(centres[branch.junctions[1]][None])
    if branch.closed:
        parts.append(branch.pixels[:1].astype(np.float64))
    return np.concatenate(parts)


def _prune_spurs(branches: list[_Branch], centres: np.ndarray, radius: np.ndarray, spur_factor: float) -> list[_Branch]:
    """Drop branches from a junction to a free end shorter than ``spur_factor`` x the local radius (px).

    A junction always keeps two branches (its longest spurs if need be), so a thick crack whose skeleton
    forks near its tip keeps its length, and the end of a crack never disappears.
    """
    spurs: dict[int, list[tuple[float, int]]] = {}
    attached: dict[int, int] = {}
    for i, b in enumerate(branches):
        for j in b.junctions:
            attached[j] = attached.get(j, 0) + (j > 0)
        if sum(b.free) == 1 and sum(j > 0 for j in b.junctions) == 1:
            j = max(b.junctions)
            r, c = np.rint(centres[j]).astype(int)
            length = float(np.linalg.norm(np.diff(_points(b, centres), axis=0), axis=1).sum())
            if length < spur_factor * max(float(radius[r, c]), 1.0):
                spurs.setdefault(j, []).append((length, i))
    dropped: set[int] = set()
    for j, found in spurs.items():
        keep = max(0, 2 - (attached[j] - len(found)))
        dropped.update(i for _, i in sorted(found)[: len(found) - keep])
    return [b for i, b in enumerate(branches) if i not in dropped]


def smooth_path(points: np.ndarray, sigma: float, closed: bool = False) -> np.ndarray:
    """Gaussian smoothing of an ordered path, ends fixed, to remove the staircase of pixel steps.

    Open paths are extended by point reflection through each end (2 p_0 - p_k), which keeps the end in
    place and a straight path straight; closed paths wrap around.

    Parameters
    ----------
    points : (N, 2) float64, ordered.
    sigma : Gaussian standard deviation along the path, in points.

    Returns
    -------
    (N, 2) float64.
    """
    if sigma <= 0 or len(points) < 3:
        return points.astype(np.float64)
    if closed:
        return ndi.gaussian_filter1d(points[:-1].astype(np.float64), sigma, axis=0, mode="wrap")[
            np.r_[np.arange(len(points) - 1), 0]
        ]
    pad = min(len(points) - 1, int(np.ceil(4 * sigma)))
    head = 2 * points[0] - points[1 : pad + 1][::-1]
    tail = 2 * points[-1] - points[-pad - 1 : -1][::-1]
    extended = np.concatenate([head, points, tail]).astype(np.float64)
    return ndi.gaussian_filter1d(extended, sigma, axis=0, mode="nearest")[pad : pad + len(points)]


def path_length(points: np.ndarray) -> float:
    """Length of a polyline (N, 2), in its own units."""
    return float(np.linalg.norm(np.diff(points, axis=0), axis=1).sum()) if len(points) > 1 else 0.0


def _owned_lengths(points: np.ndarray) -> np.ndarray:
    """(N,) the half-steps on either side of each point of a polyline (they sum to its length)."""
    steps = np.linalg.norm(np.diff(points, axis=0), axis=1)
    return np.r_[steps, 0.0] / 2 + np.r_[0.0, steps] / 2


def area_per_pixel(mask: np.ndarray, skeleton: np.ndarray, coverage: np.ndarray | None = None) -> np.ndarray:
    """(H, W) float64: on each skeleton pixel, the crack area (px) of its component nearest to it.

    Summed along a stretch of skeleton and divided by the stretch's length this is the mean width there:
    an unbiased width, unlike 2 x the distance transform, which jumps by a pixel between odd and even
    widths because it is measured between pixel centres. The area is the count of ``mask`` pixels, or with
    ``coverage`` (H, W) float in [0, 1] (see :func:`crack_coverage`) the sum of the covered shares, taken
    over the pixels ``coverage`` marks near the mask.
    """
    region = mask if coverage is None else mask | (coverage > 0)
    dist_input = np.where(skeleton, 0, 1).astype(np.uint8)
    _, nearest = cv2.distanceTransformWithLabels(
        dist_input, cv2.DIST_L2, cv2.DIST_MASK_5, labelType=cv2.DIST_LABEL_PIXEL
    )
    components = ndi.label(region, structure=EIGHT_CONNECTED)[0]
    owner = np.zeros(int(nearest.max()) + 1, dtype=np.int64)  # label of a skeleton pixel -> its flat index
    owner[nearest[skeleton]] = np.flatnonzero(skeleton)
    flat_owner = owner[nearest[region]]
    same = components.ravel()[flat_owner] == components[region]
    weights = None if coverage is None else coverage[region][same].astype(np.float64)
    counts = np.bincount(flat_owner[same], weights=weights, minlength=mask.size).astype(np.float64)
    return counts.reshape(mask.shape) * skeleton


def darkening(grey: np.ndarray, mask: np.ndarray, background_px: float) -> np.ndarray:
    """(H, W) float32 ``1 - grey / background``: how much darker each pixel is than the coating around it.

    The background is a Gaussian (``background_px``) average of the grey levels outside ``mask`` (the
    cracks), normalised by the share of non-crack pixels, so the cracks do not darken their own background.
    """
    free = (~mask).astype(np.float32)
    background = cv2.GaussianBlur(grey * free, (0, 0), background_px) / np.maximum(
        cv2.GaussianBlur(free, (0, 0), background_px), 1e-3
    )
    return (1.0 - grey / np.maximum(background, 1.0)).astype(np.float32)


def crack_coverage(
    dark: np.ndarray, mask: np.ndarray, grow_px: int = 2, floor: float = 0.1, along_px: float = 4.0
) -> np.ndarray:
    """(H, W) float32 share of each pixel a crack covers, from its darkening against the crack's core.

    A crack of width w darkens its core by some depth D and a pixel it covers by a share c by about c D,
    whatever the blur (photo, resampling), as long as the crack is wider than the blur: ``dark / D``
    summed across the crack is its width, the "equivalent width" of a line profile. D is taken along the
    mask's skeleton (the darkest of each skeleton pixel's 3 x 3 neighbours, lightly smoothed, averaged
    along the crack with a Gaussian of ``along_px``) and spread over the crack's cross-section. Pixels within
    ``grow_px`` of ``mask`` darker than ``floor`` D count; the rest 0. The detector's mask tells where a
    crack is, not how wide it is.

    Cracks narrower than about 2.5 blur sigmas never reach their full depth: their width comes out too
    large (by up to the blur's width), as any intensity-based width would.
    """
    if not mask.any():
        return np.zeros(mask.shape, np.float32)
    skeleton = thin(mask)
    radius = cv2.distanceTransform(mask.astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    window = int(min(2 * np.ceil(radius.max()) + 3 + 2 * grow_px, 41))
    core = ndi.maximum_filter(cv2.GaussianBlur(dark, (0, 0), 0.5), size=3) * skeleton
    weight = cv2.GaussianBlur(skeleton.astype(np.float32), (0, 0), along_px)
    along = cv2.GaussianBlur(core.astype(np.float32), (0, 0), along_px) / np.maximum(weight, 1e-6)
    depth = ndi.maximum_filter(np.where(skeleton, along, 0.0), size=window)
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * grow_px + 1, 2 * grow_px + 1))
    near = cv2.dilate(mask.astype(np.uint8), kernel).astype(bool)
    with np.errstate(divide="ignore", invalid="ignore"):
        share = np.where(near & (depth > 0) & (dark >= floor * depth), np.clip(dark / depth, 0.0, 1.0), 0.0)
    return share.astype(np.float32)


def principal_orientation(points: np.ndarray, weights: np.ndarray) -> float:
    """Principal-axis direction of weighted points (N, 2) (x, y-down), degrees in [0, 180), y up."""
    centre = np.average(points, axis=0, weights=weights)
    d = points - centre
    cov = (d * weights[:, None]).T @ d
    _, vectors = np.linalg.eigh(cov)
    vx, vy = vectors[:, -1]
    return float(np.degrees(np.arctan2(-vy, vx)) % 180.0)


def _local_widths(points: np.ndarray, areas: np.ndarray, free: tuple[bool, bool], half_window: int) -> np.ndarray:
    """(N,) width (px) at each path point: mask area over path length in a window of 2 half_window + 1 points.

    Points whose window reaches a free end are NaN: the mask beyond the tip of the skeleton (the end cap)
    is all counted on the end pixel and would inflate the width there.
    """
    owned = _owned_lengths(points)
    kernel = np.ones(2 * half_window + 1)
    area_sum = ndi.convolve1d(areas, kernel, mode="constant")
    length_sum = ndi.convolve1d(owned * (areas > 0), kernel, mode="constant")
    widths = np.where(length_sum > 0, area_sum / np.maximum(length_sum, 1e-9), np.nan)
    if free[0]:
        widths[: half_window + 1] = np.nan
    if free[1]:
        widths[len(widths) - half_window - 1 :] = np.nan
    return widths


def _branch_geometry(
    branch: _Branch,
    centres: np.ndarray,
    areas: np.ndarray,
    free: tuple[bool, bool],
    smoothing_px: float,
    half_window: int,
) -> tuple[np.ndarray, np.ndarray]:
    """Smoothed (M, 2) (row, col) points of a branch and their local widths (M,) px (NaN: not measured)."""
    points = smooth_path(_points(branch, centres), smoothing_px, branch.closed)
    pixel_area = areas[branch.pixels[:, 0], branch.pixels[:, 1]]
    head, tail = int(branch.junctions[0] > 0), int(branch.junctions[1] > 0) + int(branch.closed)
    area = np.concatenate([np.zeros(head), pixel_area, np.zeros(tail)])  # junction centres own no area
    return points, _local_widths(points, area, free, half_window)


def measure_cracks(
    mask: np.ndarray,
    mm_per_px: float,
    *,
    min_length_mm: float = 0.0,
    smoothing_px: float = 2.0,
    spur_factor: float = 2.0,
    width_window_px: int = 6,
    coverage: np.ndarray | None = None,
) -> list[Crack]:
    """Measure every crack (8-connected component) of a crack mask.

    Parameters
    ----------
    mask : (H, W) bool, True on crack pixels, in an orthorectified raster.
    mm_per_px : the raster's ground sampling distance, mm per pixel.
    min_length_mm : cracks shorter than this are dropped.
    smoothing_px : Gaussian sigma (in path points) smoothing each branch before its length is summed, so the
        staircase of an oblique pixel path (up to 8% too long at 22.5 degrees) does not count.
    spur_factor : branches from a junction to a free end shorter than this times the local crack radius are
        skeletonisation spurs and are dropped.
    width_window_px : half-length of the stretch of path over which a local width is averaged, in points.
    coverage : (H, W) float share of each pixel covered by a crack (:func:`crack_coverage`); widths are then
        the covered area per length instead of the mask's.

    Returns
    -------
    One :class:`Crack` per component long enough, ordered by the component's first pixel (row-major).
    """
    if mask.ndim != 2:
        raise ValueError(f"expected an (H, W) mask, got shape {mask.shape}")
    if mm_per_px <= 0:
        raise ValueError(f"mm_per_px must be positive, got {mm_per_px}")
    mask = mask.astype(bool)
    skeleton = thin(mask)
    radius = cv2.distanceTransform(mask.astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    branches, _, centres = _branches(skeleton)
    branches = _prune_spurs(branches, centres, radius, spur_factor)
    areas = area_per_pixel(mask, skeleton, coverage)
    components, _ = ndi.label(mask, structure=EIGHT_CONNECTED)
    by_component: dict[int, list[_Branch]] = {}
    for b in branches:
        by_component.setdefault(int(components[b.pixels[0, 0], b.pixels[0, 1]]), []).append(b)
    attached = np.bincount([j for b in branches for j in b.junctions], minlength=len(centres))
    boxes = ndi.find_objects(components)
    cracks = []
    for label in sorted(by_component):
        crack = _measure_one(
            by_component[label], centres, areas, attached, boxes[label - 1], mm_per_px, smoothing_px, width_window_px
        )
        if crack.length_mm >= min_length_mm:
            cracks.append(crack)
    return cracks


def _measure_one(
    branches: list[_Branch],
    centres: np.ndarray,
    areas: np.ndarray,
    attached: np.ndarray,
    box: tuple[slice, slice],
    mm_per_px: float,
    smoothing_px: float,
    half_window: int,
) -> Crack:
    """One crack from its branches (pixel units in, mm out)."""
    paths, widths, ends = [], [], []
    for b in branches:
        free = tuple(f or (j > 0 and attached[j] == 1) for f, j in zip(b.free, b.junctions, strict=True))
        points, local = _branch_geometry(b, centres, areas, (free[0], free[1]), smoothing_px, half_window)
        paths.append(points)
        widths.append(local)
        ends += [p for p, f in zip((points[0], points[-1]), free, strict=True) if f and not b.closed]
    owned = np.concatenate([_owned_lengths(p) for p in paths])
    all_widths = np.concatenate(widths)
    valid = np.isfinite(all_widths)
    if not valid.any():  # too short for any window clear of the tips: area over length, caps included
        total_area = sum(float(areas[b.pixels[:, 0], b.pixels[:, 1]].sum()) for b in branches)
        all_widths, valid = np.full(len(owned), total_area / max(float(owned.sum()), 1.0)), np.ones(len(owned), bool)
    xy = [p[:, ::-1] * mm_per_px for p in paths]  # (row, col) px -> (x, y) mm
    points = np.concatenate(xy)
    return Crack(
        paths_mm=tuple(xy),
        length_mm=sum(path_length(p) for p in xy),
        mean_width_mm=float(np.average(all_widths[valid], weights=owned[valid] + 1e-12)) * mm_per_px,
        max_width_mm=float(all_widths[valid].max()) * mm_per_px,
        orientation_deg=principal_orientation(points, owned + 1e-12),
        endpoints_mm=np.array(ends, dtype=np.float64).reshape(-1, 2)[:, ::-1] * mm_per_px,
        bbox_mm=(
            box[1].start * mm_per_px,
            box[0].start * mm_per_px,
            (box[1].stop - 1) * mm_per_px,
            (box[0].stop - 1) * mm_per_px,
        ),
    )


def length_histogram(cracks: Sequence[Crack], bin_edges_mm: Sequence[float] = DEFAULT_LENGTH_BINS_MM) -> np.ndarray:
    """(B,) int64 number of cracks per length bin; ``bin_edges_mm`` (B + 1,) increasing, the last may be inf."""
    edges = np.asarray(bin_edges_mm, dtype=np.float64)
    if edges.ndim != 1 or len(edges) < 2 or np.any(np.diff(edges) <= 0):
        raise ValueError("bin_edges_mm must be at least two increasing values")
    lengths = np.array([c.length_mm for c in cracks], dtype=np.float64)
    index = np.searchsorted(edges, lengths, side="right") - 1  # bins closed on the left, like np.histogram's
    inside = (index >= 0) & (index < len(edges) - 1)
    return np.bincount(index[inside], minlength=len(edges) - 1).astype(np.int64)


def summarise_cracks(cracks: Sequence[Crack], bin_edges_mm: Sequence[float] = DEFAULT_LENGTH_BINS_MM) -> CrackSummary:
    """Count, total length, length-weighted mean width, max width and the length histogram of ``cracks``."""
    lengths = np.array([c.length_mm for c in cracks], dtype=np.float64)
    total = float(lengths.sum())
    mean_width = float(np.dot(lengths, [c.mean_width_mm for c in cracks]) / total) if total > 0 else 0.0
    return CrackSummary(
        count=len(cracks),
        total_length_mm=total,
        mean_width_mm=mean_width,
        max_width_mm=max((c.max_width_mm for c in cracks), default=0.0),
        histogram_edges_mm=np.asarray(bin_edges_mm, dtype=np.float64),
        histogram_counts=length_histogram(cracks, bin_edges_mm),
    )


def sample_crack(crack: Crack, step_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """Points every <= ``step_mm`` along all branches of a crack.

    Returns
    -------
    points : (M, 2) float64 (x, y) mm.
    weights : (M,) float64 mm of crack each point stands for (they sum to ``crack.length_mm``).
    """
    points, weights = [], []
    for path in crack.paths_mm:
        if len(path) < 2:
            continue
        steps = np.linalg.norm(np.diff(path, axis=0), axis=1)
        along = np.r_[0.0, np.cumsum(steps)]
        s = np.linspace(0.0, along[-1], max(2, int(np.ceil(along[-1] / step_mm)) + 1))
        resampled = np.column_stack([np.interp(s, along, path[:, 0]), np.interp(s, along, path[:, 1])])
        points.append(resampled)
        weights.append(_owned_lengths(resampled))
    if not points:
        return np.zeros((0, 2)), np.zeros(0)
    return np.concatenate(points), np.concatenate(weights)


def overlap_fraction(crack: Crack, other: Crack, tolerance_mm: float) -> float:
    """Fraction of ``crack``'s length that lies within ``tolerance_mm`` of ``other`` (0 to 1)."""
    points, weights = sample_crack(crack, tolerance_mm / 2)
    other_points, _ = sample_crack(other, tolerance_mm / 4)
    if not len(points) or not len(other_points) or weights.sum() <= 0:
        return 0.0
    distance, _ = cKDTree(other_points).query(points, distance_upper_bound=tolerance_mm)
    return float(weights[distance <= tolerance_mm].sum() / weights.sum())


def _boxes_near(a: Crack, b: Crack, margin: float) -> bool:
    ax0, ay0, ax1, ay1 = a.bbox_mm
    bx0, by0, bx1, by1 = b.bbox_mm
    return ax0 - margin <= bx1 and bx0 - margin <= ax1 and ay0 - margin <= by1 and by0 - margin <= ay1


def match_cracks(
    previous: Sequence[Crack],
    current: Sequence[Crack],
    tolerance_mm: float,
    *,
    min_overlap: float = 0.5,
    min_growth_mm: float | None = None,
) -> list[CrackMatch]:
    """Relate the cracks of a load stage to those of the stage before (same specimen raster, in mm).

    A previous crack continues in the current crack that covers the largest part of it, if at least
    ``min_overlap`` of its length lies within ``tolerance_mm`` of that current crack (several previous
    cracks may join into one). A current crack continuing none is ``new``; else its growth is its length
    minus theirs, and it is ``grown`` when that exceeds ``min_growth_mm`` (default ``tolerance_mm``,
    below which length differences are measurement noise), ``unchanged`` otherwise.

    Returns
    -------
    One :class:`CrackMatch` per current crack, in order.
    """
    if tolerance_mm <= 0:
        raise ValueError(f"tolerance_mm must be positive, got {tolerance_mm}")
    threshold = tolerance_mm if min_growth_mm is None else min_growth_mm
    continues: dict[int, list[int]] = {i: [] for i in range(len(current))}
    for j, old in enumerate(previous):
        overlaps = [
            (overlap_fraction(old, new, tolerance_mm) if _boxes_near(old, new, tolerance_mm) else 0.0, i)
            for i, new in enumerate(current)
        ]
        best, i = max(overlaps, default=(0.0, -1))
        if best >= min_overlap:
            continues[i].append(j)
    matches = []
    for i, crack in enumerate(current):
        if not continues[i]:
            matches.append(CrackMatch(i, "new", crack.length_mm, ()))
            continue
        growth = max(0.0, crack.length_mm - sum(previous[j].length_mm for j in continues[i]))
        matches.append(CrackMatch(i, "grown" if growth > threshold else "unchanged", growth, tuple(continues[i])))
    return matches


def background_px(mm_per_px: float) -> float:
    """Scale of the coating's local grey level around a crack, px: 2 mm, at least 4 px."""
    return max(2.0 / mm_per_px, 4.0)


# below this width (photo px across the crack) a crack's profile is the photo's pixel and blur whatever its
# width: its width rests on the coating's contrast alone (``profile.crack_widths``) and is flagged, with the
# range it may lie in. Rendered hairlines (``tests/crack_scenes.py``, 0.5 px PSF, 30 % contrast, 45 degrees,
# seeds 7, 11, 13, 31) of 1.5 photo px measure 1.34-1.47 px, of 2 px 1.83-2.02 px
RESOLVED_WIDTH_PX = 1.7
# one sigma of a resolved crack's width, photo px plus a share of the width: the profile widths of those
# scenes' cracks of 2-4 photo px are off by 0.02-0.03 mm rms (0.05-0.07 px), up to 0.11 mm where an oblique
# view blurs the crack most (the contrast of a crack taken as the coating's, 30 % for all there)
WIDTH_SPREAD_PX = 0.08
WIDTH_SPREAD_SHARE = 0.03


@dataclass(frozen=True)
class WidthEstimate:
    """A crack's width as the photos can tell it."""

    width_mm: float
    # one sigma; for a crack below photo resolution, the half-width of an interval around ``width_mm`` that
    # holds every width it may have, 0 to ``RESOLVED_WIDTH_PX`` photo pixels
    uncertainty_mm: float
    below_photo_resolution: bool  # the photos do not resolve its width


def estimate_width(width_mm: float, photo_mm_per_px: float) -> WidthEstimate:
    """A crack's width (its mean width from its profile, ``measure_cracks``' stage) as the photos, of sampling
    ``photo_mm_per_px`` across the crack, can tell it, with an uncertainty.

    A crack narrower than ``RESOLVED_WIDTH_PX`` photo pixels blurs into the photo's pixel and PSF: its width
    is its equivalent width (its darkness deficit over the coating's crack contrast), right only as far as
    its contrast is the coating's, so it is flagged and its uncertainty covers all it may be, 0 to
    ``RESOLVED_WIDTH_PX`` photo pixels. Wider cracks keep their width, with ``WIDTH_SPREAD_PX`` photo pixels
    plus ``WIDTH_SPREAD_SHARE`` of the width as one sigma, as measured on rendered cracks.

    Parameters
    ----------
    width_mm : measured mean width, mm.
    photo_mm_per_px : the photos' sampling across the crack where it is, mm per photo pixel (> 0).
    """
    if photo_mm_per_px <= 0:
        raise ValueError(f"photo_mm_per_px must be positive, got {photo_mm_per_px}")
    limit = RESOLVED_WIDTH_PX * photo_mm_per_px
    if width_mm < limit:
        width = max(width_mm, 0.0)
        return WidthEstimate(width, max(width, limit - width), True)
    return WidthEstimate(width_mm, WIDTH_SPREAD_PX * photo_mm_per_px + WIDTH_SPREAD_SHARE * width_mm, False)
