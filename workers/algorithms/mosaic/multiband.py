"""Seams and multiband blending (Burt & Adelson 1983; Brown & Lowe 2007, sec. 6; OpenCV's
``detail::GraphCutSeamFinder`` and ``detail::MultiBandBlender``).

Every mosaic pixel is owned by one frame: the owners come from a graph cut through the overlaps on a
low-resolution render (a frame's footprint about 0.1 MP there, as cv2.Stitcher's; the cut runs where the
frames' colours agree, so a car or a tree's parallax ends up whole on one side; a max-flow of our own graph,
PyMaxflow's, since OpenCV's finder cut through such a car). Each output window is then blended band by band:
the frames' Laplacian pyramids weighted by the Gaussian pyramids of their ownership, so fine detail switches
sharply at the seam and coarse brightness blends over a wide band. A window is composed with a margin wide
enough for the coarsest band, so window edges never show and memory stays that of a window.
"""

from __future__ import annotations

from collections.abc import Callable

import cv2
import numpy as np

from workers.algorithms.mosaic.alignment import apply_homography, frame_corners
from workers.algorithms.mosaic.blending import feather_weights, warp_maps

SEAM_FRAME_PX = 1e5  # px of a frame's footprint on the render the seams are cut on (cv2.Stitcher's 0.1 MP)
SEAM_MAX_PX = 2048  # longest side of that render, at most
SEAM_GAP = 10  # render px beyond a pair's shared box that its graph spans (as OpenCV's GraphCutSeamFinder)
SEAM_EDGE_COST = 1e6  # a cut between render px not both in the overlap: it would run along a frame's edge
TIED = 1e12  # a frame's pixel outside the overlap: its own, whatever the cut costs
SEAM_SUPERSAMPLE = 3  # colour differences sampled s x s times a render px; a cut's cost is their mean
SOFT_KERNEL = np.array([0.25, 0.5, 0.25], np.float32)  # ownership smoothed over a render px either side

Box = tuple[int, int, int, int]  # (x0, y0, x1, y1) render px


def seam_labels(
    image_of: Callable[[int], np.ndarray],
    sizes: dict[int, tuple[int, int]],
    to_frame: dict[int, np.ndarray],
    gains: dict[int, np.ndarray],
    width: int,
    height: int,
) -> tuple[np.ndarray, float]:
    """(lh, lw) int32 owner of every pixel of a low-resolution render of the output grid (-1: no frame) and
    that render's scale (low-res px per output px, :func:`seam_scale`).

    Frames are sampled SEAM_SUPERSAMPLE^2 times a render px (uint8, 27 B a px), each over its own box, so
    memory is that of the frames' footprints on the render (about SEAM_FRAME_PX each), not of the render; the
    overlaps are then cut pair by pair on the gain-corrected colours (:func:`_cut_pairs`), the colours the
    mosaic will show.
    """
    r = seam_scale(sizes, to_frame, width, height)
    lw, lh = max(1, round(width * r)), max(1, round(height * r))
    low_to_out = np.diag([1 / r, 1 / r, 1.0])
    keys = sorted(to_frame)
    boxes, images, masks = [], [], []
    for k in keys:
        x0, y0, x1, y1 = _render_box(to_frame[k] @ low_to_out, sizes[k], lw, lh)
        map_x, map_y = warp_maps(to_frame[k] @ low_to_out, x0, y0, x1 - x0, y1 - y0)
        inside = feather_weights(map_x, map_y, *sizes[k], 1.0) > 0
        pixels = np.zeros((*inside.shape, 3 * SEAM_SUPERSAMPLE**2), np.uint8)
        if inside.any():
            image, to_k = image_of(k), to_frame[k] @ low_to_out
            samples = [_sample_low(image, *warp_maps(to_k @ s, x0, y0, x1 - x0, y1 - y0)) for s in _sub_samples()]
            pixels = np.concatenate(samples, axis=2)
        boxes.append((x0, y0, x1, y1))
        images.append(pixels)
        masks.append(inside)
    _cut_pairs(images, [gains[k] for k in keys], masks, boxes)
    labels = np.full((lh, lw), -1, np.int32)
    for n in range(len(keys) - 1, -1, -1):  # a pixel left to two frames goes to the first
        _crop(labels, (0, 0, lw, lh), boxes[n])[masks[n]] = keys[n]
    return labels, r


def _sub_samples() -> list[np.ndarray]:
    """(3, 3) shifts of the render's px centres to SEAM_SUPERSAMPLE^2 points evenly spread over each px."""
    offsets = [(i + 0.5) / SEAM_SUPERSAMPLE - 0.5 for i in range(SEAM_SUPERSAMPLE)]
    return [np.array([[1.0, 0.0, dx], [0.0, 1.0, dy], [0.0, 0.0, 1.0]]) for dy in offsets for dx in offsets]


def _cut_pairs(images: list[np.ndarray], gains: list[np.ndarray], masks: list[np.ndarray], boxes: list[Box]) -> None:
    """Cut each overlap between its two frames, pair after pair in order, as OpenCV's ``PairwiseSeamFinder``
    does: a minimum graph cut (Boykov-Kolmogorov's max-flow, PyMaxflow) over the pair's shared box and SEAM_GAP
    px around it. ``masks`` (bool, over each frame's box) lose the pixels the other frame keeps.

    The cost of cutting between two neighbours is the squared length of the frames' colour difference (8-bit
    levels, gain-corrected) at each, plus 1, as OpenCV's ``GraphCutSeamFinder`` COST_COLOR, but the mean over
    ``images``' SEAM_SUPERSAMPLE^2 samples of each px instead of one: where fine detail disagrees (parallax,
    a slight misregistration) a single bilinear sample often happens to agree, and the cut ran through
    texture that then showed a step (seam visibility on Brighton / budapest1-6 / the synthetic flight
    0.715 / 0.827 / 0.773 with one sample, 0.687 / 0.707 / 0.716 with 2 x 2, 0.640 / 0.691 / 0.776 with 3 x 3,
    0.642 / 0.720 / 0.752 with 4 x 4; blurring the frames before sampling instead took them to 0.79-0.98, the
    cut no longer seeing the texture). A frame's pixels outside the
    overlap are tied to it, and a cut beside a pixel outside the overlap costs SEAM_EDGE_COST. OpenCV's finder
    (its own terminal weights 1e4 and edge penalty 1e3) cut straight through a car that one frame shows, or a
    patch of any brightness step, where it lay on the shortest way across an overlap
    (``tests/unit/test_multiband.py``); with its gradient cost (COST_COLOR_GRAD) the cuts ran along the
    ground's edges, where a step across the line shows most (seam visibility 1.03-1.04 on budapest and the
    synthetic flight, cut at 512 px; 0.95-1.35 at 0.1 MP a frame; 0.75 with this cut, ``bench/seams.py``).
    """
    import maxflow  # type: ignore[import-untyped]

    right = np.array([[0, 0, 0], [0, 0, 1], [0, 0, 0]])
    down = np.array([[0, 0, 0], [0, 0, 0], [0, 1, 0]])
    for i in range(len(images)):
        for j in range(i + 1, len(images)):
            bi, bj = boxes[i], boxes[j]
            shared = (max(bi[0], bj[0]), max(bi[1], bj[1]), min(bi[2], bj[2]), min(bi[3], bj[3]))
            if shared[2] <= shared[0] or shared[3] <= shared[1]:
                continue
            if not (_crop(masks[i], bi, shared) & _crop(masks[j], bj, shared)).any():
                continue
            union = (min(bi[0], bj[0]), min(bi[1], bj[1]), max(bi[2], bj[2]), max(bi[3], bj[3]))
            region = (max(shared[0] - SEAM_GAP, union[0]), max(shared[1] - SEAM_GAP, union[1]),
                      min(shared[2] + SEAM_GAP, union[2]), min(shared[3] + SEAM_GAP, union[3]))  # fmt: skip
            a, b = _over(masks[i], bi, region), _over(masks[j], bj, region)
            both = a & b
            d = _gained(_over(images[i], bi, region), gains[i]) - _gained(_over(images[j], bj, region), gains[j])
            cost = np.where(both, np.einsum("ijk,ijk->ij", d, d) / SEAM_SUPERSAMPLE**2, 0.0)
            outside = ~both
            across = np.zeros(both.shape)  # the edge from each px to its right, then lower, neighbour
            across[:, :-1] = cost[:, :-1] + cost[:, 1:] + 1.0 + SEAM_EDGE_COST * (outside[:, :-1] | outside[:, 1:])
            along = np.zeros(both.shape)
            along[:-1] = cost[:-1] + cost[1:] + 1.0 + SEAM_EDGE_COST * (outside[:-1] | outside[1:])
            graph = maxflow.GraphFloat()
            nodes = graph.add_grid_nodes(both.shape)
            graph.add_grid_edges(nodes, weights=across, structure=right, symmetric=True)
            graph.add_grid_edges(nodes, weights=along, structure=down, symmetric=True)
            graph.add_grid_tedges(nodes, np.where(a & ~b, TIED, 0.0), np.where(b & ~a, TIED, 0.0))
            graph.maxflow()
            to_j = graph.get_grid_segments(nodes)  # the sink's side: j keeps these
            for n, box, lost in ((i, bi, both & to_j), (j, bj, both & ~to_j)):
                mine = _inside(region, box)
                _crop(masks[n], box, mine)[_crop(lost, region, mine)] = False


def _gained(samples: np.ndarray, gain: np.ndarray) -> np.ndarray:
    """(h, w, 3 n) float32 colours of a frame's sub-samples (uint8, n colours a px) times its per-channel gain."""
    return samples.astype(np.float32) * np.tile(gain.astype(np.float32), samples.shape[2] // 3)


def _inside(region: Box, box: Box) -> Box:
    """The part of ``region`` inside ``box``."""
    return max(region[0], box[0]), max(region[1], box[1]), min(region[2], box[2]), min(region[3], box[3])


def _crop(array: np.ndarray, box: Box, region: Box) -> np.ndarray:
    """The view of ``array`` (laid over ``box``) over ``region``, which lies inside the box."""
    return array[region[1] - box[1] : region[3] - box[1], region[0] - box[0] : region[2] - box[0]]


def _over(array: np.ndarray, box: Box, region: Box) -> np.ndarray:
    """A copy of ``array`` (laid over ``box``) over ``region``, zero (False) where the box does not reach."""
    out = np.zeros((region[3] - region[1], region[2] - region[0], *array.shape[2:]), array.dtype)
    part = _inside(region, box)
    if part[2] > part[0] and part[3] > part[1]:
        _crop(out, region, part)[...] = _crop(array, box, part)
    return out


def _render_box(to_frame: np.ndarray, size: tuple[int, int], width: int, height: int) -> Box:
    """Render px box of a frame of ``size`` px (``to_frame``: render px -> its px), a px to spare, clipped to
    the render, at least one px."""
    c = apply_homography(np.linalg.inv(to_frame), frame_corners(*size))
    x0, y0 = np.floor(c.min(axis=0)).astype(int) - 1
    x1, y1 = np.ceil(c.max(axis=0)).astype(int) + 1
    x0, y0 = min(max(int(x0), 0), width - 1), min(max(int(y0), 0), height - 1)
    return x0, y0, max(min(int(x1), width), x0 + 1), max(min(int(y1), height), y0 + 1)


def seam_scale(sizes: dict[int, tuple[int, int]], to_frame: dict[int, np.ndarray], width: int, height: int) -> float:
    """Low-resolution px per output px of the render the seams are cut on: a frame's mean footprint there is
    SEAM_FRAME_PX (as cv2.Stitcher's seam_est_resol), the whole render at most SEAM_MAX_PX on its longest side."""
    areas = [abs(_shoelace(apply_homography(np.linalg.inv(to_frame[k]), frame_corners(*sizes[k])))) for k in sizes]
    per_frame = np.sqrt(SEAM_FRAME_PX / max(float(np.mean(areas)), 1.0)) if areas else 1.0
    return float(min(1.0, per_frame, SEAM_MAX_PX / max(width, height)))


def _shoelace(polygon: np.ndarray) -> float:
    x, y = polygon[:, 0], polygon[:, 1]
    return 0.5 * float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))


def _sample_low(image: np.ndarray, map_x: np.ndarray, map_y: np.ndarray) -> np.ndarray:
    """Bilinear samples of ``image`` at the maps, reading only the rows and columns they reach."""
    c0 = max(int(np.floor(np.nanmin(map_x))) - 1, 0)
    r0 = max(int(np.floor(np.nanmin(map_y))) - 1, 0)
    c1 = min(int(np.ceil(np.nanmax(map_x))) + 2, image.shape[1])
    r1 = min(int(np.ceil(np.nanmax(map_y))) + 2, image.shape[0])
    if c1 <= c0 or r1 <= r0:
        return np.zeros((*map_x.shape, 3), image.dtype)
    crop = np.ascontiguousarray(image[r0:r1, c0:c1])
    return cv2.remap(crop, map_x - c0, map_y - r0, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


def margin_px(bands: int) -> int:
    """Margin a window is blended with so its bands are what the whole mosaic's would be there: 3 px of the
    coarsest level. Each pyrDown's 5-tap kernel reaches 2 px of its level, so an exact margin is the sum of
    2^(l+1) output px over the levels plus 2^bands (158 px for 5 bands against 96); what lies beyond 96 px
    reaches a window's edge only through the kernels' outer taps (1/16 each): on the Brighton strip the mosaic
    differs from the exact margin's by 0.005 levels on average, by more than 1 at 7 px in a million, 3 at most,
    and multiband's CPU fell by a third (the padded window of a 512 px window 828^2 -> 704^2 px)."""
    return 3 * 2**bands


LabelWindow = tuple[np.ndarray, int, int]  # labels' cells, the column and row of its first cell


def label_window(labels: np.ndarray, scale: float, window: tuple[int, int, int, int]) -> LabelWindow:
    """The cells of the low-resolution ``labels`` (at ``scale``) that an output ``window``'s bilinear
    :func:`ownership` reads, with two cells to spare (its smoothing reads one more): (cells, first column,
    first row). At the labels' edge, the edge cells (which the warp replicates)."""
    x, y, w, h = window
    lh, lw = labels.shape
    lx0 = min(max(int(np.floor((x + 0.5) * scale - 0.5)) - 2, 0), lw - 1)
    ly0 = min(max(int(np.floor((y + 0.5) * scale - 0.5)) - 2, 0), lh - 1)
    lx1 = max(min(int(np.floor((x + w - 0.5) * scale - 0.5)) + 4, lw), lx0 + 1)
    ly1 = max(min(int(np.floor((y + h - 0.5) * scale - 0.5)) + 4, lh), ly0 + 1)
    return labels[ly0:ly1, lx0:lx1], lx0, ly0


def ownership(
    labels: np.ndarray, scale: float, k: int, window: tuple[int, int, int, int], near: LabelWindow | None = None
) -> np.ndarray:
    """(h, w) float32 in [0, 1]: where frame ``k`` owns output ``window``, the low-resolution labels brought
    smoothed over a cell either side and brought to full resolution bilinearly (a seam about two cells wide,
    which the bands then shape; one cell wide showed more on Brighton, 0.72 against 0.70). ``near``: the
    window's :func:`label_window`, when already cut."""
    x, y, w, h = window
    cells, lx0, ly0 = label_window(labels, scale, window) if near is None else near
    owned = (cells == k).astype(np.float32)
    # smoothed over a render px either side: the finest band switches over about two render px, not one
    owned = cv2.sepFilter2D(owned, -1, SOFT_KERNEL, SOFT_KERNEL, borderType=cv2.BORDER_REPLICATE)
    # output pixel centre (x + i + 0.5) -> low-res pixel centre coordinate (x + i + 0.5) * scale - 0.5
    M = np.array([[scale, 0.0, (x + 0.5) * scale - 0.5 - lx0], [0.0, scale, (y + 0.5) * scale - 0.5 - ly0]])
    flags = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
    return cv2.warpAffine(owned, M, (w, h), flags=flags, borderMode=cv2.BORDER_REPLICATE)


def blend_bands(
    images: list[np.ndarray],
    weights: list[np.ndarray],
    bands: int,
    corners: list[tuple[int, int]] | None = None,
    size: tuple[int, int] | None = None,
) -> np.ndarray:
    """Multiband blend of (h, w, 3) float32 ``images`` by (h, w) float32 ``weights``: band l of the result is
    the weights' Gaussian level l average of the images' Laplacian band l. Returns (h, w, 3) float32.

    With ``corners`` and ``size`` (w, h), each image and its weight covers only part of the result, from its
    corner (x, y): a frame's pyramids are built over the part its weight reaches, not the whole window. Each
    corner is a multiple of 2^bands px and each part ends at the result's edge or is a multiple of 2^bands px
    wide and high, so its levels fall on the result's levels' px.

    OpenCV's array operations throughout: NumPy's broadcasting of a weight over 3 channels cost as much as
    the pyramids."""
    w, h = (images[0].shape[1], images[0].shape[0]) if size is None else size
    corners = [(0, 0)] * len(images) if corners is None else corners
    shapes = [(h, w)]
    for _ in range(bands):
        shapes.append(((shapes[-1][0] + 1) // 2, (shapes[-1][1] + 1) // 2))
    acc = [np.zeros((*shape, 3), np.float32) for shape in shapes]
    wsum = [np.zeros(shape, np.float32) for shape in shapes]
    for image, weight, (cx, cy) in zip(images, weights, corners, strict=True):
        if cx % 2**bands or cy % 2**bands:
            raise ValueError(f"a part's corner ({cx}, {cy}) is not on the coarsest level's px")
        lap = _laplacian_pyramid(image, bands)
        gauss = _gaussian_pyramid(weight, bands)
        for level, (band, g) in enumerate(zip(lap, gauss, strict=True)):
            x0, y0 = cx >> level, cy >> level
            view = (slice(y0, y0 + g.shape[0]), slice(x0, x0 + g.shape[1]))
            if acc[level][view].shape[:2] != g.shape:
                raise ValueError("a part neither ends at the result's edge nor spans whole coarsest px")
            cv2.add(acc[level][view], cv2.multiply(band, cv2.merge([g, g, g])), dst=acc[level][view])
            cv2.add(wsum[level][view], g, dst=wsum[level][view])
    levels = []
    for a, s in zip(acc, wsum, strict=True):
        inverse = cv2.divide(1.0, np.maximum(s, np.float32(1e-6)))
        levels.append(cv2.multiply(a, cv2.merge([inverse, inverse, inverse])))
    out = levels[-1]
    for band in reversed(levels[:-1]):
        out = cv2.add(cv2.pyrUp(out, dstsize=(band.shape[1], band.shape[0])), band)
    return out[:h, :w]


def _gaussian_pyramid(image: np.ndarray, bands: int) -> list[np.ndarray]:
    levels = [image]
    for _ in range(bands):
        levels.append(cv2.pyrDown(levels[-1]))
    return levels


def _laplacian_pyramid(image: np.ndarray, bands: int) -> list[np.ndarray]:
    gauss = _gaussian_pyramid(image, bands)
    out = [
        cv2.subtract(fine, cv2.pyrUp(coarse, dstsize=(fine.shape[1], fine.shape[0])))
        for fine, coarse in zip(gauss[:-1], gauss[1:], strict=True)
    ]
    return [*out, gauss[-1]]


def owned_regions(labels: np.ndarray, scale: float) -> dict[int, list[np.ndarray]]:
    """Frame -> outline rings (N, 2) of the region it owns, output px, traced on the labels' render."""
    out: dict[int, list[np.ndarray]] = {}
    for k in np.unique(labels[labels >= 0]).tolist():
        contours, _ = cv2.findContours((labels == k).astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
        rings = [(c.reshape(-1, 2).astype(np.float64) + 0.5) / scale for c in contours if len(c) >= 3]
        if rings:
            out[int(k)] = rings
    return out


def seam_points(labels: np.ndarray, scale: float, limit: int = 2000) -> tuple[np.ndarray, np.ndarray]:
    """Points on the cut lines, output px (x, y), and the unit normal across the seam at each: where the owner
    changes between horizontal or vertical neighbours of the labels' render. At most ``limit``, evenly taken."""
    points, normals = [], []
    across_x = (labels[:, 1:] != labels[:, :-1]) & (labels[:, 1:] >= 0) & (labels[:, :-1] >= 0)
    rows, cols = np.nonzero(across_x)
    points.append(np.column_stack([(cols + 1) / scale, (rows + 0.5) / scale]))
    normals.append(np.tile([1.0, 0.0], (len(rows), 1)))
    across_y = (labels[1:, :] != labels[:-1, :]) & (labels[1:, :] >= 0) & (labels[:-1, :] >= 0)
    rows, cols = np.nonzero(across_y)
    points.append(np.column_stack([(cols + 0.5) / scale, (rows + 1) / scale]))
    normals.append(np.tile([0.0, 1.0], (len(rows), 1)))
    p, n = np.concatenate(points), np.concatenate(normals)
    keep = np.unique(np.linspace(0, len(p) - 1, min(limit, len(p))).astype(int)) if len(p) else np.zeros(0, int)
    return p[keep], n[keep]


def seam_visibility(
    read: Callable[[int, int, int, int], tuple[np.ndarray, np.ndarray]],
    points: np.ndarray,
    normals: np.ndarray,
    offset_px: int = 16,
) -> float | None:
    """How much the cut lines show in a mosaic: the mean colour step across them (between the pixels 1 px
    either side) over the same step measured ``offset_px`` to either side, parallel to the seam (1.0: the
    seam is as invisible as any line of the ground; feathering's and multiband's on the same seams compare).

    ``read(x, y, w, h)`` gives a window of the mosaic, (h, w, 3) and its (h, w) coverage; points whose profile
    leaves the coverage are skipped. None without any usable point.
    """
    steps, references = [], []
    reach = offset_px + 2
    for (x, y), (nx, _) in zip(points, normals, strict=True):
        cx, cy = int(np.floor(x)), int(np.floor(y))
        if nx:  # seam between columns cx - 1 and cx: a row of pixels across it
            pixels, mask = read(cx - reach, cy, 2 * reach, 1)
            line, ok = pixels[0].astype(np.float64), mask[0]
        else:
            pixels, mask = read(cx, cy - reach, 1, 2 * reach)
            line, ok = pixels[:, 0].astype(np.float64), mask[:, 0]
        if len(line) < 2 * reach or not ok.all():
            continue
        # the seam lies between line[reach - 1] and line[reach]; colour steps between neighbours, per px
        jumps = np.abs(np.diff(line, axis=0)).mean(axis=1)  # jumps[i]: between line[i] and line[i + 1]
        steps.append(float(jumps[reach - 1]))
        references.append(0.5 * float(jumps[reach - 1 - offset_px] + jumps[reach - 1 + offset_px]))
    if not steps or np.mean(references) <= 0:
        return None
    return float(np.mean(steps) / np.mean(references))
