"""Orthorectification geometry of a posed camera over a ground plane ``Z = z0``: the part of its frame that
sees the ground nearby (frames that see the horizon are cut below it, since ground far away is smeared
over a huge area by the projection); and over a surface gridded from the adjusted tie points, the maps that
render a frame as if its ground were that plane (its relief displacement removed)."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy import interpolate, ndimage, spatial

from workers.algorithms.geometry import Camera

MIN_KEPT_ROWS = 0.1  # a frame cut to less than this share of its rows (or columns) is left out


def ground_crop(
    R: np.ndarray, C: np.ndarray, z0: float, camera: Camera, max_range: float
) -> tuple[int, int, int, int] | None:
    """The part of the frame, ``(x0, y0, x1, y1)`` px (end exclusive), that sees the ground nearby.

    A pixel qualifies if its ray meets the plane ``z0`` in front of the camera within ``max_range``
    flying heights of the nadir point. That region of the plane is a disk, so its image is convex and
    a rectangle whose four corners qualify lies wholly inside it. The whole frame when it qualifies;
    else the frame with one edge moved in as little as needed; None when less than
    ``MIN_KEPT_ROWS`` of the frame would remain.
    """
    height = C[2] - z0
    to_world = R.T @ np.linalg.inv(camera.matrix())  # pixel -> ray direction in the world

    def corners_ok(x0: float, y0: float, x1: float, y1: float) -> bool:
        px = np.array([[x0, y0, 1], [x1 - 1, y0, 1], [x1 - 1, y1 - 1, 1], [x0, y1 - 1, 1]], float)
        rays = px @ to_world.T
        if np.any(rays[:, 2] >= -1e-9):  # level or upwards: never meets the ground in front
            return False
        reach = height / -rays[:, 2]  # ray length to the plane
        return bool(np.all(np.linalg.norm(rays[:, :2] * reach[:, None], axis=1) <= max_range * height))

    w, h = camera.width, camera.height
    if corners_ok(0, 0, w, h):
        return 0, 0, w, h
    best: tuple[int, int, int, int] | None = None
    for edge in range(4):  # move the top, bottom, left or right edge inwards
        size = h if edge < 2 else w
        lo, hi = 0, int(size * (1 - MIN_KEPT_ROWS))
        if not corners_ok(*_moved(edge, hi, w, h)):
            continue
        while hi - lo > 1:  # smallest move that qualifies
            mid = (lo + hi) // 2
            lo, hi = (lo, mid) if corners_ok(*_moved(edge, mid, w, h)) else (mid, hi)
        crop = _moved(edge, hi, w, h)
        if best is None or _area(crop) > _area(best):
            best = crop
    return best


def _moved(edge: int, by: int, w: int, h: int) -> tuple[int, int, int, int]:
    return [(0, by, w, h), (0, 0, w, h - by), (by, 0, w, h), (0, 0, w - by, h)][edge]


def _area(crop: tuple[int, int, int, int]) -> int:
    return (crop[2] - crop[0]) * (crop[3] - crop[1])


# -- A surface from the tie points ------------------------------------------------------------------------

MIN_SURFACE_POINTS = 20  # fewer adjusted tie points make no surface: the plane is used
OUTLIER_SIGMAS = 5.0  # a cell this many robust sigmas from the cells around it is dropped ...
OUTLIER_FLOOR_CELLS = 0.5  # ... if also farther than this many cell widths (a slope's own spread)
NEIGHBOUR_CELLS = 3.0  # the cells within this many cell widths are a cell's neighbours


@dataclass(frozen=True, eq=False)
class GroundSurface:
    """Heights on a regular grid of the world frame: ``heights`` (H, W) float64, cell (row, col) centred on
    (x0 + col * cell, y0 + row * cell), metres (rows grow northwards)."""

    heights: np.ndarray
    x0: float
    y0: float
    cell: float

    def height_at(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Bilinear height at world (x, y); outside the grid, the nearest edge's."""
        rows, cols = self.heights.shape
        fx = np.clip((np.asarray(x, np.float64) - self.x0) / self.cell, 0.0, cols - 1.0)
        fy = np.clip((np.asarray(y, np.float64) - self.y0) / self.cell, 0.0, rows - 1.0)
        j0, i0 = (
            np.minimum(np.floor(fx).astype(np.int64), cols - 2),
            np.minimum(np.floor(fy).astype(np.int64), rows - 2),
        )
        j0, i0 = np.maximum(j0, 0), np.maximum(i0, 0)
        tx, ty = fx - j0, fy - i0
        h = self.heights
        j1, i1 = np.minimum(j0 + 1, cols - 1), np.minimum(i0 + 1, rows - 1)
        top = h[i0, j0] * (1 - tx) + h[i0, j1] * tx
        bottom = h[i1, j0] * (1 - tx) + h[i1, j1] * tx
        return np.asarray(top * (1 - ty) + bottom * ty)


def ground_surface(points: np.ndarray, smooth_cells: float = 0.5) -> GroundSurface | None:
    """A smooth surface through adjusted tie points (N, 3), or None with fewer than ``MIN_SURFACE_POINTS``.

    The cell is twice the points' mean spacing over their bounding box; each cell takes the median height of
    its points (a wrong point does not pull it), a cell far from the median of the cells around it, or with
    none around it, is dropped (it holds only wrong points), cells without points are interpolated linearly
    between the others (the nearest one's beyond their hull), then the grid is smoothed by a Gaussian of
    ``smooth_cells`` cells. It stands for the ground the photos show, not for its detail: a surface the
    orthorectification projects onto instead of one plane.
    """
    pts = np.asarray(points, np.float64).reshape(-1, 3)
    pts = pts[np.isfinite(pts).all(axis=1)]
    if len(pts) < MIN_SURFACE_POINTS:
        return None
    lo, hi = pts[:, :2].min(axis=0), pts[:, :2].max(axis=0)
    area = max(float(np.prod(hi - lo)), 1e-6)
    cell = 2.0 * float(np.sqrt(area / len(pts)))
    cols, rows = (np.floor((hi - lo) / cell).astype(int) + 1).tolist()
    index = np.floor((pts[:, :2] - lo) / cell).astype(int)
    flat = index[:, 1] * cols + index[:, 0]
    order = np.argsort(flat, kind="stable")
    cells, starts = np.unique(flat[order], return_index=True)
    medians = np.array([np.median(part) for part in np.split(pts[order, 2], starts[1:])])
    grid_x, grid_y = np.meshgrid(np.arange(cols), np.arange(rows))
    known = np.column_stack([cells % cols, cells // cols]).astype(np.float64)
    keep = _consistent(known, medians, cell)
    if keep.sum() >= 3:
        known, medians = known[keep], medians[keep]
    heights = _interpolate(known, medians, grid_x, grid_y)
    if smooth_cells > 0:
        heights = ndimage.gaussian_filter(heights, smooth_cells, mode="nearest")
    return GroundSurface(heights, float(lo[0] + 0.5 * cell), float(lo[1] + 0.5 * cell), cell)


def _consistent(known: np.ndarray, medians: np.ndarray, cell: float) -> np.ndarray:
    """(K,) bool: the cells that agree with the other cells within ``NEIGHBOUR_CELLS`` of them. A cell with no
    other around it (a lone point past the others) or far from their median holds only wrong points (a
    mismatch triangulated hundreds of metres off)."""
    tree = spatial.cKDTree(known)
    around = np.full(len(known), np.nan)
    for k, near in enumerate(tree.query_ball_point(known, NEIGHBOUR_CELLS)):
        others = [j for j in near if j != k]
        if others:
            around[k] = np.median(medians[others])
    off = np.abs(medians - around)
    finite = np.isfinite(off)
    if not finite.any():
        return finite
    limit = max(OUTLIER_SIGMAS * 1.4826 * float(np.median(off[finite])), OUTLIER_FLOOR_CELLS * cell)
    return finite & (off <= limit)


def _interpolate(known: np.ndarray, values: np.ndarray, grid_x: np.ndarray, grid_y: np.ndarray) -> np.ndarray:
    """Linear between the known cells (Delaunay), the nearest known cell's value elsewhere."""
    nearest = interpolate.griddata(known, values, (grid_x, grid_y), method="nearest")
    if len(known) < 3:
        return np.asarray(nearest, np.float64)
    try:
        linear = interpolate.griddata(known, values, (grid_x, grid_y), method="linear")
    except spatial.QhullError:  # the cells on one line
        return np.asarray(nearest, np.float64)
    return np.asarray(np.where(np.isfinite(linear), linear, nearest), np.float64)


def relief_maps(
    R: np.ndarray,
    C: np.ndarray,
    camera: Camera,
    z0: float,
    crop: tuple[int, int, int, int],
    surface: GroundSurface,
) -> tuple[np.ndarray, np.ndarray]:
    """``cv2.remap`` maps that render a frame as if its ground were the plane ``Z = z0``.

    Pixel (x, y) of the output (the undistorted frame's pixels inside ``crop``) stands for the plane point
    its ray meets, (X, Y, z0); the map sends it to where the camera sees the surface's point above or below
    it, (X, Y, surface(X, Y)), in the frame as photographed (``camera`` with its distortion). The rendered frame
    and the plane are then related by the same homography as the plane's own rectification, so composing
    is unchanged, but ground off the plane lands at its map position instead of being displaced by its
    relief. Occlusions are not resolved (the surface is smooth). Where the surface's point lies outside the
    photo (relief above the plane near the frame's far edges), the plane's point is sampled instead: its relief
    displacement stays there, where the photo's border repeated had streaked the mosaic (on the Brighton strip,
    along the wood at its outer edge).

    R, C : the frame's pose, ``X_cam = R (X - C)``; camera : its adjusted camera, with distortion
    Returns (y1 - y0, x1 - x0) float32 maps into the photographed frame.
    """
    x0, y0, x1, y1 = crop
    ideal = camera.replace(k1=0.0, k2=0.0, k3=0.0, t1=0.0, t2=0.0)
    u, v = np.meshgrid(np.arange(x0, x1, dtype=np.float64), np.arange(y0, y1, dtype=np.float64))
    rays = np.column_stack([u.ravel(), v.ravel(), np.ones(u.size)]) @ (R.T @ np.linalg.inv(ideal.matrix())).T
    t = (z0 - C[2]) / rays[:, 2]
    ground = C + t[:, None] * rays
    ground[:, 2] = surface.height_at(ground[:, 0], ground[:, 1])
    seen = camera.project((ground - C) @ R.T)
    # where the surface's point lies outside the photo (relief above the plane, near the frame's far edge), the
    # plane's: its border repeated would streak the mosaic there
    outside = ~camera.in_frame(seen)
    plane = ground[outside]
    plane[:, 2] = z0
    seen[outside] = camera.project((plane - C) @ R.T)
    shape = (y1 - y0, x1 - x0)
    return seen[:, 0].reshape(shape).astype(np.float32), seen[:, 1].reshape(shape).astype(np.float32)


# -- A surface from dense stereo ----------------------------------------------------------------------------

MIN_CELL_POINTS = 3  # one pair's points give a cell a height when at least this many fall in it
DENSE_OUTLIER_SIGMAS = 5.0  # a fused cell this many robust sigmas from the median of the 5 x 5 cells around ...
DENSE_OUTLIER_FLOOR_M = 0.25  # ... and farther than this (the spread of a clean surface's own cells) is dropped
FILL_SIGMA_CELLS = 3.0  # the dense surface's offset from the base fades over this many cells past its edge
MAX_DENSE_CELLS = 16_000_000  # a finer grid than this is coarsened


@dataclass(frozen=True)
class CellGrid:
    """A regular grid of the world frame: ``rows`` x ``cols`` cells of ``cell`` m, (0, 0) at the south-west
    corner ``(x0, y0)`` (its cell spans x0 .. x0 + cell), rows northwards."""

    x0: float
    y0: float
    cell: float
    rows: int
    cols: int


def dense_grid(base: GroundSurface, xy: np.ndarray, cell: float) -> CellGrid:
    """A grid of ``cell`` metres spanning the ``base`` surface and the points ``xy`` (M, 2) (the ground the
    frames see), coarsened to at most ``MAX_DENSE_CELLS`` cells."""
    rows0, cols0 = base.heights.shape
    lo = np.array([base.x0, base.y0]) - 0.5 * base.cell
    hi = lo + base.cell * np.array([cols0, rows0])
    xy = np.asarray(xy, np.float64).reshape(-1, 2)
    xy = xy[np.isfinite(xy).all(axis=1)]
    if len(xy):
        lo, hi = np.minimum(lo, xy.min(axis=0)), np.maximum(hi, xy.max(axis=0))
    cell = max(float(cell), float(np.sqrt(np.prod(hi - lo) / MAX_DENSE_CELLS)))
    cols, rows = (np.floor((hi - lo) / cell).astype(int) + 1).tolist()
    return CellGrid(float(lo[0]), float(lo[1]), cell, rows, cols)


def cell_medians(points: np.ndarray, grid: CellGrid) -> tuple[np.ndarray, np.ndarray]:
    """One pair's dense points (N, 3) reduced to the grid: (K,) int64 flat cell indices (row * cols + col) and
    (K,) float64 median heights of the cells with ``MIN_CELL_POINTS`` or more points (points off the grid and
    not finite are left out). Reducing each pair as it comes keeps a long flight's points out of memory."""
    pts = np.asarray(points, np.float64).reshape(-1, 3)
    pts = pts[np.isfinite(pts).all(axis=1)]
    index = np.floor((pts[:, :2] - [grid.x0, grid.y0]) / grid.cell).astype(np.int64)
    inside = (index[:, 0] >= 0) & (index[:, 0] < grid.cols) & (index[:, 1] >= 0) & (index[:, 1] < grid.rows)
    flat = index[inside, 1] * grid.cols + index[inside, 0]
    return _medians(flat, pts[inside, 2], MIN_CELL_POINTS)


def _medians(flat: np.ndarray, values: np.ndarray, min_count: int) -> tuple[np.ndarray, np.ndarray]:
    """The distinct keys of ``flat`` with ``min_count`` or more values, and the median of their values."""
    order = np.lexsort((values, flat))  # by cell, then by value within it
    z, flat = values[order], flat[order]
    cells, starts, counts = np.unique(flat, return_index=True, return_counts=True)
    enough = counts >= min_count
    starts, counts = starts[enough], counts[enough]
    return cells[enough], 0.5 * (z[starts + (counts - 1) // 2] + z[starts + counts // 2])


def dense_surface(
    cells: np.ndarray, heights: np.ndarray, base: GroundSurface, grid: CellGrid, smooth_cells: float = 1.0
) -> tuple[GroundSurface, np.ndarray]:
    """A surface on ``grid`` from the cell heights of dense stereo pairs, and its cells they measured,
    (rows, cols) bool.

    ``cells``, ``heights`` (K,): every pair's ``cell_medians`` together. A cell takes the median over the pairs
    that measured it (a wrong pair does not pull it); a cell far from the cells around it is dropped. Cells
    without a height take the ``base`` surface's (the tie points'), shifted near measured cells by the
    measured cells' offset from it (a normalised Gaussian of ``FILL_SIGMA_CELLS``, fading to the base where no
    cell is near), so the two meet without a step; the grid is then smoothed by a Gaussian of ``smooth_cells``.
    """
    flat = np.full(grid.rows * grid.cols, np.nan)
    fused, values = _medians(np.asarray(cells, np.int64), np.asarray(heights, np.float64), 1)
    flat[fused] = values
    measured = flat.reshape(grid.rows, grid.cols)
    centre_x = grid.x0 + (np.arange(grid.cols) + 0.5) * grid.cell
    centre_y = grid.y0 + (np.arange(grid.rows) + 0.5) * grid.cell
    below = base.height_at(*np.meshgrid(centre_x, centre_y))
    known = np.isfinite(measured)
    known &= ~_off_neighbours(np.where(known, measured, below), known)
    offset = np.where(known, measured - below, 0.0)
    weight = ndimage.gaussian_filter(known.astype(np.float64), FILL_SIGMA_CELLS, mode="constant")
    spread = ndimage.gaussian_filter(offset, FILL_SIGMA_CELLS, mode="constant")
    fade = np.clip(weight / 0.25, 0.0, 1.0)  # a lone measured cell shifts its surroundings only partly
    filled = below + np.where(weight > 1e-6, spread / np.maximum(weight, 1e-6), 0.0) * fade
    heights_out = np.where(known, measured, filled)
    if smooth_cells > 0:
        heights_out = ndimage.gaussian_filter(heights_out, smooth_cells, mode="nearest")
    return GroundSurface(heights_out, float(centre_x[0]), float(centre_y[0]), grid.cell), known


def _off_neighbours(heights: np.ndarray, known: np.ndarray) -> np.ndarray:
    """(rows, cols) bool: measured cells far from the median of the 5 x 5 cells around them (a mismatch)."""
    if not known.any():
        return np.zeros_like(known)
    off = np.abs(heights - ndimage.median_filter(heights, size=5, mode="nearest"))
    limit = max(DENSE_OUTLIER_SIGMAS * 1.4826 * float(np.median(off[known])), DENSE_OUTLIER_FLOOR_M)
    return known & (off > limit)


# -- The surface as a raster (an ortho job's DSM) ------------------------------------------------------------

SURFACE_NO_DATA, SURFACE_MEASURED, SURFACE_INTERPOLATED = 0, 1, 2  # the states of ``surface_raster``'s cells


@dataclass(frozen=True)
class RasterGrid:
    """A north-up raster of the world frame: ``rows`` x ``cols`` square cells of ``cell`` m, its north-west
    corner at world ``(x0, y0)``; cell (row, col) is centred on (x0 + (col + 0.5) cell, y0 - (row + 0.5) cell)."""

    x0: float
    y0: float
    cell: float
    rows: int
    cols: int

    def px(self, xy: np.ndarray) -> np.ndarray:
        """(N, 2) world x, y -> (N, 2) float raster (col, row), cell corners on whole numbers."""
        xy = np.asarray(xy, np.float64).reshape(-1, 2)
        return np.column_stack([(xy[:, 0] - self.x0) / self.cell, (self.y0 - xy[:, 1]) / self.cell])


def surface_raster(
    surface: GroundSurface,
    measured: np.ndarray | None,
    points: np.ndarray,
    footprints: list[np.ndarray],
    grid: RasterGrid,
) -> tuple[np.ndarray, np.ndarray]:
    """The surface sampled on ``grid`` where it rests on measurements, with the state of each cell.

    A cell has a height where it is *measured* (a dense cell of ``measured`` covers its centre, or a tie point
    of ``points`` falls in it) or *interpolated*: inside the convex hull of the tie points and seen by two or
    more frames (``footprints``: each frame's ground, a convex (K, 2) world x, y polygon), where stereo could
    reach. Elsewhere (the surface's edge, extrapolated from the nearest heights) it has none.

    surface : the surface frames were projected onto; measured : (rows, cols) bool over ``surface.heights``, the
    cells dense stereo measured, or None (a tie points' surface); points : (N, 3) adjusted tie points.
    Returns (grid.rows, grid.cols) float32 heights, NaN where none, and uint8 states (``SURFACE_NO_DATA``,
    ``SURFACE_MEASURED``, ``SURFACE_INTERPOLATED``).
    """
    shape = (grid.rows, grid.cols)
    cols, rows = np.meshgrid(np.arange(grid.cols), np.arange(grid.rows))
    x, y = grid.x0 + (cols + 0.5) * grid.cell, grid.y0 - (rows + 0.5) * grid.cell
    hit = np.zeros(shape, bool)
    pts = np.asarray(points, np.float64).reshape(-1, 3)
    pts = pts[np.isfinite(pts).all(axis=1)]
    at = np.floor(grid.px(pts[:, :2])).astype(np.int64)
    on = (at[:, 0] >= 0) & (at[:, 0] < grid.cols) & (at[:, 1] >= 0) & (at[:, 1] < grid.rows)
    hit[at[on, 1], at[on, 0]] = True
    if measured is not None:
        j = np.rint((x - surface.x0) / surface.cell).astype(np.int64)
        i = np.rint((y - surface.y0) / surface.cell).astype(np.int64)
        inside = (i >= 0) & (i < measured.shape[0]) & (j >= 0) & (j < measured.shape[1])
        hit[inside] |= measured[i[inside], j[inside]]
    support = _convex_fill(grid.px(pts[:, :2]), shape) if len(pts) >= 3 else np.zeros(shape, bool)
    support &= _seen_twice([grid.px(f) for f in footprints], shape)
    state = np.where(hit, SURFACE_MEASURED, np.where(support, SURFACE_INTERPOLATED, SURFACE_NO_DATA)).astype(np.uint8)
    heights = np.where(state > 0, surface.height_at(x, y), np.nan).astype(np.float32)
    return heights, state


def _convex_fill(px: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """(H, W) bool: the cells whose centres lie in the convex hull of raster points ``px`` (N, 2)."""
    mask = np.zeros(shape, np.uint8)
    if len(px) < 3 or not np.isfinite(px).all():
        return mask.astype(bool)
    hull = cv2.convexHull(np.round((px - 0.5) * 16).astype(np.int32))  # 4 fractional bits, centres on whole px
    cv2.fillConvexPoly(mask, hull, 1, lineType=cv2.LINE_8, shift=4)
    return mask.astype(bool)


def _seen_twice(polygons: list[np.ndarray], shape: tuple[int, int]) -> np.ndarray:
    """(H, W) bool: the cells inside two or more of the convex raster polygons, each (K, 2)."""
    counts = np.zeros(shape, np.int32)
    for poly in polygons:
        lo = np.clip(np.floor(poly.min(axis=0)).astype(int) - 1, 0, None)
        hi = np.minimum(np.ceil(poly.max(axis=0)).astype(int) + 1, [shape[1], shape[0]])
        if np.any(hi <= lo):
            continue
        part = _convex_fill(poly - lo, (int(hi[1] - lo[1]), int(hi[0] - lo[0])))
        counts[lo[1] : hi[1], lo[0] : hi[0]] += part
    return counts >= 2
