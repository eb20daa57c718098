"""The surface a crack survey is rectified onto, and which of its points a photo sees.

A :class:`Surface` is a raster over a plane (:class:`~workers.algorithms.specimen.mesh.PlaneFrame`): pixel
(col, row) is centred on the plane point ``(x, y) = (col, row) * mm_per_px`` and holds the specimen's
height ``h`` above it, so its model point is ``frame.to_model((x, y, h))``. A plate is its own plane
(``h = 0``, nothing hides anything). A mesh is rasterised orthographically onto its plane: each pixel
takes the height of the surface layer on the cameras' side (a z-buffer along the plane's normal).

What a photo sees of a mesh is decided by a second z-buffer, in the photo: the index of the nearest
triangle at each photo pixel (:class:`PhotoDepth`); a surface point is hidden when the ray to it meets
that triangle's plane clearly before reaching it. Both z-buffers rasterise with ``cv2.fillConvexPoly``
and interpolate depth per pixel (1 / depth in the photo, perspective-correct for a pinhole; the lens
distortion bends a large triangle's edges, which moves the buffer's boundaries by a pixel or so).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import cv2
import numpy as np

from workers.algorithms.geometry import Camera, world_to_camera
from workers.algorithms.specimen.mesh import Mesh, PlaneFrame

_SUBPIXEL_BITS = 4  # fillConvexPoly's fixed-point vertices: 1/16 px
OCCLUSION_TOLERANCE = 0.01  # a point is hidden only if something lies more than 1% of its distance before it


# Lanczos rather than bilinear or bicubic: where the output is finer than the photo, those draw the photo's
# pixel lattice as streaks that the crack detector takes for hairline cracks
INTERPOLATION = cv2.INTER_LANCZOS4
BLOCK_PIXELS = 1 << 20  # raster pixels mapped at once: bounds the memory of the maps (~60 B per pixel)


@dataclass(frozen=True)
class Surface:
    """The specimen's surface sampled on a plane raster (see the module's docstring)."""

    frame: PlaneFrame
    height: np.ndarray  # (H, W) float32 height above the plane, mm; NaN where the specimen is not
    mm_per_px: float
    mesh: Mesh | None = None  # a mesh specimen's triangles (for occlusion); None for a plate

    @property
    def shape(self) -> tuple[int, int]:
        return (int(self.height.shape[0]), int(self.height.shape[1]))

    def points(self, rows: slice = slice(None)) -> np.ndarray:
        """(h, W, 3) float64 model mm of the raster pixels of ``rows`` (NaN off the specimen)."""
        height = self.height[rows].astype(np.float64)
        r = np.arange(self.shape[0])[rows]
        x, y = np.meshgrid(np.arange(self.shape[1]) * self.mm_per_px, r * self.mm_per_px)
        return self.frame.to_model(np.stack([x, y, height], axis=-1))

    @cached_property
    def flat(self) -> bool:
        """Every height is 0: the surface is its plane (a plate)."""
        return not np.any(self.height)

    def normals(self, rows: slice = slice(None)) -> np.ndarray:
        """(h, W, 3) float64 unit model normals of ``rows`` (toward +N), from the height map's slopes."""
        if self.flat:
            return np.broadcast_to(self.frame.axes[2], (*self.height[rows].shape, 3))
        dx, dy = self._slopes
        dx, dy = dx[rows], dy[rows]
        local = np.stack([-dx, -dy, np.ones_like(dx)], axis=-1)
        return (local / np.linalg.norm(local, axis=-1, keepdims=True)) @ self.frame.axes

    @cached_property
    def _slopes(self) -> tuple[np.ndarray, np.ndarray]:
        """(dh/dx, dh/dy), (H, W) float64 each; 0 at the edge of a mesh (the plane's normal there)."""
        if min(self.shape) < 2:
            return np.zeros(self.shape), np.zeros(self.shape)
        dy, dx = np.gradient(self.height.astype(np.float64), self.mm_per_px)
        flat = ~(np.isfinite(dx) & np.isfinite(dy))
        return np.where(flat, 0.0, dx), np.where(flat, 0.0, dy)

    def lift(self, xy: np.ndarray) -> np.ndarray:
        """(N, 2) plane (x, y) mm -> (N, 3) model mm on the surface (height interpolated bilinearly)."""
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        if self.flat:
            return self.frame.to_model(xy)
        px = (xy / self.mm_per_px).astype(np.float32)
        h = cv2.remap(
            self._filled_height,
            px[:, 0].reshape(-1, 1),
            px[:, 1].reshape(-1, 1),
            cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_REPLICATE,
        ).ravel()
        return self.frame.to_model(np.column_stack([xy, h]))

    def width_stretch(self, xy: np.ndarray, tangents: np.ndarray) -> np.ndarray:
        """(N,) how much longer on the surface than on the plane a short step across a line is, at plane
        points ``xy`` (N, 2) mm where the line runs along ``tangents`` (N, 2): ``sqrt(1 + slope^2)`` of
        the surface across the line (1 on a plate)."""
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        if self.flat:
            return np.ones(len(xy))
        across = np.asarray(tangents, dtype=np.float64).reshape(-1, 2)[:, ::-1] * [-1.0, 1.0]
        across /= np.maximum(np.linalg.norm(across, axis=1, keepdims=True), 1e-12)
        col = np.clip(np.rint(xy[:, 0] / self.mm_per_px).astype(int), 0, self.shape[1] - 1)
        row = np.clip(np.rint(xy[:, 1] / self.mm_per_px).astype(int), 0, self.shape[0] - 1)
        dx, dy = self._slopes
        slope = dx[row, col] * across[:, 0] + dy[row, col] * across[:, 1]
        return np.sqrt(1.0 + slope**2)

    @cached_property
    def _filled_height(self) -> np.ndarray:
        """(H, W) float32 heights with the nearest surface height off the surface (to sample at its edge)."""
        return np.where(np.isfinite(self.height), self.height, _nearest_fill(self.height)).astype(np.float32)


def raster_shape(width_mm: float, height_mm: float, mm_per_px: float) -> tuple[int, int]:
    """(rows, cols) of a raster with pixel centres every ``mm_per_px`` from 0 to the given extents."""
    return (math.floor(height_mm / mm_per_px + 1e-9) + 1, math.floor(width_mm / mm_per_px + 1e-9) + 1)


def plate_surface(width_mm: float, height_mm: float, mm_per_px: float) -> Surface:
    """A plate in its own frame: X right, Y down, Z = 0 on the surface."""
    frame = PlaneFrame(np.zeros(3), np.eye(3))
    return Surface(frame, np.zeros(raster_shape(width_mm, height_mm, mm_per_px), np.float32), mm_per_px)


def mesh_surface(mesh: Mesh, frame: PlaneFrame, mm_per_px: float, camera_side: np.ndarray) -> Surface:
    """``mesh`` rasterised onto ``frame`` at ``mm_per_px``: per pixel, the height of the layer nearest the
    side of the plane where ``camera_side`` (3,) model mm, a camera centre, lies.

    Triangles seen edge-on from the plane's normal (walls) cover no pixel and are left out.
    """
    plane = frame.to_plane(mesh.vertices)
    shape = raster_shape(float(plane[:, 0].max()), float(plane[:, 1].max()), mm_per_px)
    corners = plane[mesh.triangles]  # (T, 3, 3) plane (x, y, h)
    coefficients, flat = _height_planes(corners)
    side = 1.0 if frame.to_plane(np.asarray(camera_side).reshape(1, 3))[0, 2] >= corners[..., 2].mean() else -1.0
    ids = rasterise(corners[..., :2] / mm_per_px, -side * corners[..., 2], np.flatnonzero(~flat), shape)
    x, y = np.meshgrid(np.arange(shape[1]) * mm_per_px, np.arange(shape[0]) * mm_per_px)
    a, b, c = coefficients[np.maximum(ids, 0)].transpose(2, 0, 1)
    height = np.where(ids >= 0, a * x + b * y + c, np.nan).astype(np.float32)
    return Surface(frame, height, mm_per_px, mesh)


def _height_planes(corners: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per triangle (T, 3, 3) plane (x, y, h): coefficients (T, 3) of ``h = a x + b y + c`` and (T,) bool
    True for triangles whose projection on the plane has (almost) no area."""
    design = np.concatenate([corners[..., :2], np.ones((*corners.shape[:2], 1))], axis=2)  # (T, 3, 3)
    det = np.linalg.det(design)
    extent = np.ptp(corners[..., :2], axis=1).max(axis=1)
    flat = np.abs(det) <= 1e-9 * np.maximum(extent, 1e-12) ** 2
    safe = np.where(flat[:, None, None], np.eye(3), design)
    return np.linalg.solve(safe, corners[..., 2:3])[..., 0], flat


def rasterise(
    triangles_px: np.ndarray,
    depth: np.ndarray,
    candidates: np.ndarray,
    shape: tuple[int, int],
    perspective: bool = False,
) -> np.ndarray:
    """(H, W) int32 index of the nearest triangle over each pixel (-1: none): a z-buffer.

    Parameters
    ----------
    triangles_px : (T, 3, 2) float64 pixel (x, y) corners, pixel centres at integers.
    depth : (T, 3) float64 depth of each corner (smaller is nearer), > 0 if ``perspective``.
    candidates : (K,) int indices of the triangles to draw.
    shape : (H, W) of the raster.
    perspective : interpolate 1 / depth across a triangle (a camera's view) instead of depth (orthographic).
    """
    ids = np.full(shape, -1, np.int32)
    nearest = np.full(shape, np.inf)
    fixed = np.rint(triangles_px * (1 << _SUBPIXEL_BITS)).astype(np.int64)
    values = 1.0 / depth if perspective else depth
    for t in candidates:
        lo = np.maximum(np.floor(triangles_px[t].min(axis=0)).astype(int), 0)
        hi = np.minimum(np.ceil(triangles_px[t].max(axis=0)).astype(int) + 1, [shape[1], shape[0]])
        if np.any(hi <= lo):
            continue
        canvas = np.zeros((hi[1] - lo[1], hi[0] - lo[0]), np.uint8)
        cv2.fillConvexPoly(canvas, (fixed[t] - (lo << _SUBPIXEL_BITS)).astype(np.int32), 1, cv2.LINE_8, _SUBPIXEL_BITS)
        rows, cols = np.nonzero(canvas)
        if len(rows) == 0:
            continue
        weights = _barycentric(triangles_px[t], np.column_stack([cols + lo[0], rows + lo[1]]))
        value = weights @ values[t]
        z = 1.0 / value if perspective else value
        rows, cols = rows + lo[1], cols + lo[0]
        closer = z < nearest[rows, cols]
        nearest[rows[closer], cols[closer]] = z[closer]
        ids[rows[closer], cols[closer]] = t
    return ids


def _barycentric(corners: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(N, 3) barycentric weights of ``points`` (N, 2) in the triangle ``corners`` (3, 2), clipped to it (a
    pixel the rasteriser takes at an edge may lie a little outside)."""
    a, b, c = corners
    basis = np.column_stack([b - a, c - a])
    if abs(np.linalg.det(basis)) < 1e-12:
        return np.full((len(points), 3), 1.0 / 3.0)
    uv = np.linalg.solve(basis, (points - a).T).T
    weights = np.clip(np.column_stack([1.0 - uv.sum(axis=1), uv]), 0.0, None)
    return weights / weights.sum(axis=1, keepdims=True)


@dataclass(frozen=True)
class PhotoDepth:
    """The nearest triangle of a mesh at every pixel of one photo, and the triangles' planes (model frame)."""

    camera: Camera
    R: np.ndarray
    C: np.ndarray
    ids: np.ndarray  # (h, w) int32 triangle index, -1 where no triangle is seen
    normals: np.ndarray  # (T, 3) float64 unit normals
    offsets: np.ndarray  # (T,) float64, n . X on the triangle's plane

    def visible(self, points: np.ndarray, uv: np.ndarray | None = None) -> np.ndarray:
        """(N,) bool: the photo sees each of ``points`` (N, 3) model mm (nothing of the mesh in front of it).

        Points outside the photo or behind the camera are not visible. ``uv`` (N, 2): their photo pixels, if
        already projected (points in front of the camera only).
        """
        if uv is None:
            cam = world_to_camera(points, self.R, self.C)
            front = cam[:, 2] > 1e-9
            uv = np.full((len(points), 2), -1.0)
            uv[front] = self.camera.project(cam[front])
        else:
            front = np.ones(len(points), bool)
        col, row = np.rint(uv[:, 0]).astype(np.int64), np.rint(uv[:, 1]).astype(np.int64)
        inside = front & (col >= 0) & (col < self.ids.shape[1]) & (row >= 0) & (row < self.ids.shape[0])
        result = inside.copy()
        t = np.full(len(points), -1)
        t[inside] = self.ids[row[inside], col[inside]]
        check = t >= 0
        ray = points[check] - self.C
        n = self.normals[t[check]]
        with np.errstate(divide="ignore", invalid="ignore"):
            hit = (self.offsets[t[check]] - n @ self.C) / np.einsum("ij,ij->i", n, ray)
        # hit: where along the ray (the point at 1) the seen triangle's plane lies; NaN/inf: parallel
        result[check] = ~(np.isfinite(hit) & (hit > 0) & (hit < 1 - OCCLUSION_TOLERANCE))
        return result


def photo_depth(mesh: Mesh, camera: Camera, R: np.ndarray, C: np.ndarray) -> PhotoDepth:
    """The z-buffer of ``mesh`` in the photo of the oriented ``camera``.

    Triangles with a corner behind the camera or projected far outside the frame (where the distortion
    polynomial no longer describes the lens) are left out.
    """
    cam = world_to_camera(mesh.vertices, R, C)
    front = cam[:, 2] > 1e-9
    uv = np.full((len(cam), 2), np.nan)
    uv[front] = camera.project(cam[front])
    margin = np.array([camera.width, camera.height], dtype=np.float64)
    near = front & np.all((uv > -margin) & (uv < 2 * margin), axis=1)
    usable = near[mesh.triangles].all(axis=1)
    ids = rasterise(
        np.nan_to_num(uv)[mesh.triangles],
        np.maximum(cam[mesh.triangles, 2], 1e-9),
        np.flatnonzero(usable),
        (camera.height, camera.width),
        perspective=True,
    )
    corners = mesh.corners()
    normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-300)
    return PhotoDepth(camera, R, C, ids, normals, np.einsum("ij,ij->i", normals, corners[:, 0]))


def rectification_maps(
    camera: Camera, R: np.ndarray, C: np.ndarray, surface: Surface, rows: slice, depth: PhotoDepth | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``cv2.remap`` maps that render a photo onto the raster rows ``rows`` of ``surface``, and how well the
    photo sees each point.

    On a flat surface without a mesh (a plate) the maps are smooth: they are computed every
    ``COARSE_STEP`` pixels and interpolated bilinearly (off by under 0.01 photo px, see the tests), unless
    the plane runs behind the camera within the block.

    Returns
    -------
    map_x, map_y : (h, W) float32 photo pixel (x, y) of each raster pixel, with distortion.
    density : (h, W) float32 photo pixels per mm^2 of surface there (``f^2 cos(incidence) / distance^2``);
        0 where the photo does not see the point (off the specimen, outside the frame, hidden by ``depth``).
    """
    if surface.mesh is None and surface.flat:
        coarse = _plane_maps(camera, R, C, surface, rows)
        if coarse is not None:
            return coarse
    points = surface.points(rows)
    uv, density, seen = _sample(camera, R, C, points, surface.normals(rows))
    if depth is not None and seen.any():
        seen[seen] = depth.visible(points[seen], uv[seen])
    return uv[..., 0], uv[..., 1], np.where(seen, density, 0.0).astype(np.float32)


def _sample(
    camera: Camera, R: np.ndarray, C: np.ndarray, points: np.ndarray, normals: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Photo pixel (h, w, 2) float32, sampling density (h, w) float32 and (h, w) bool "in front and inside
    the frame" of model points (h, w, 3) (NaN: none) with unit normals (h, w, 3)."""
    shape = points.shape[:2]
    flat_points = points.reshape(-1, 3)
    on = np.all(np.isfinite(flat_points), axis=1)
    safe = np.where(on[:, None], flat_points, 0.0)
    cam = world_to_camera(safe, R, C)
    front = on & (cam[:, 2] > 1e-9)
    uv = np.full((len(safe), 2), -1e6)
    uv[front] = camera.project(cam[front])
    view = C - safe
    distance = np.linalg.norm(view, axis=1)
    cos_incidence = np.abs(np.einsum("ij,ij->i", normals.reshape(-1, 3), view)) / distance
    density = camera.fx * camera.fy * cos_incidence / distance**2
    uv32 = uv.reshape(*shape, 2).astype(np.float32)
    return uv32, density.reshape(shape).astype(np.float32), front.reshape(shape) & camera.in_frame(uv32)


COARSE_STEP = 8  # raster pixels between the exactly computed nodes of a plate's maps


def _plane_maps(
    camera: Camera, R: np.ndarray, C: np.ndarray, surface: Surface, rows: slice
) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """The maps of a flat surface's ``rows`` from nodes every ``COARSE_STEP`` px, bilinearly; None when a
    node lies behind the camera (the horizon crosses the block: the maps are not smooth there)."""
    first, stop, _ = rows.indices(surface.shape[0])
    height, width = stop - first, surface.shape[1]
    node_rows = first + COARSE_STEP * np.arange(-(-(height - 1) // COARSE_STEP) + 1)
    node_cols = COARSE_STEP * np.arange(-(-(width - 1) // COARSE_STEP) + 1)
    x, y = np.meshgrid(node_cols * surface.mm_per_px, node_rows * surface.mm_per_px)
    points = surface.frame.to_model(np.stack([x, y, np.zeros_like(x)], axis=-1))
    if np.any(world_to_camera(points.reshape(-1, 3), R, C)[:, 2] <= 1e-9):
        return None
    normals = np.broadcast_to(surface.frame.axes[2], points.shape)
    uv, density, _ = _sample(camera, R, C, points, normals)
    # node (i, j) sits at block pixel (row i * step, col j * step): remap samples the node grid there
    grid_x, grid_y = np.meshgrid(
        np.arange(width, dtype=np.float32) / COARSE_STEP, np.arange(height, dtype=np.float32) / COARSE_STEP
    )
    fine = [
        cv2.remap(a, grid_x, grid_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        for a in (uv[..., 0], uv[..., 1], density)
    ]
    seen = camera.in_frame(np.stack(fine[:2], axis=-1))
    return fine[0], fine[1], np.where(seen, fine[2], 0.0).astype(np.float32)


def _nearest_fill(values: np.ndarray) -> np.ndarray:
    """``values`` (H, W) with every NaN replaced by the nearest finite value (for sampling at the edge)."""
    missing = ~np.isfinite(values)
    if not missing.any() or missing.all():
        return np.nan_to_num(values)
    _, labels = cv2.distanceTransformWithLabels(
        missing.astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_5, labelType=cv2.DIST_LABEL_PIXEL
    )
    finite_values = np.zeros(int(labels.max()) + 1, np.float64)
    finite_values[labels[~missing]] = values[~missing]
    return finite_values[labels]


def compose_views(
    camera: Camera, views: list[tuple[np.ndarray, np.ndarray, np.ndarray]], surface: Surface, compose: str
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One load step's photos ``(image, R, C)`` on the raster of ``surface``, in blocks of rows.

    ``best``: each output pixel from the photo with the highest sampling density there (the most frontal
    and nearest view); ``average``: the mean of all photos that see it.
    Returns (H, W, 3) uint8 BGR, (H, W) bool True where at least one photo sees the specimen, and (H, W)
    float32 the highest sampling density there (photo pixels per mm^2).
    """
    shape = surface.shape
    image = np.zeros((*shape, 3), np.uint8)
    best = np.zeros(shape, np.float32)  # the highest density of a photo at each pixel
    count = np.zeros(shape, np.float32) if compose == "average" else None
    total = np.zeros((*shape, 3), np.float32) if compose == "average" else None
    step = max(1, BLOCK_PIXELS // shape[1])
    for photo, R, C in views:
        depth = photo_depth(surface.mesh, camera, R, C) if surface.mesh is not None else None
        for top in range(0, shape[0], step):
            rows = slice(top, min(top + step, shape[0]))
            map_x, map_y, density = rectification_maps(camera, R, C, surface, rows, depth)
            warped = cv2.remap(photo, map_x, map_y, INTERPOLATION, borderMode=cv2.BORDER_REPLICATE)
            if total is None or count is None:
                np.copyto(image[rows], warped, where=(density > best[rows])[..., None])
            else:
                seen = density > 0
                np.add(total[rows], warped, out=total[rows], where=seen[..., None])
                count[rows] += seen
            np.maximum(best[rows], density, out=best[rows])
    if total is not None and count is not None:
        for top in range(0, shape[0], step):  # the mean, block by block: no full-size temporaries
            rows = slice(top, min(top + step, shape[0]))
            mean = total[rows] / np.maximum(count[rows], 1.0)[..., None]
            image[rows] = np.clip(np.rint(mean), 0, 255).astype(np.uint8)
    return image, best > 0, best


def photo_sampling(camera: Camera, poses: list[tuple[np.ndarray, np.ndarray]], surface: Surface) -> float:
    """The photos' own sampling on the specimen, mm per photo pixel: the median over the points of
    ``surface`` some photo sees of ``1 / sqrt(density)`` (see :func:`rectification_maps`), each point taken
    from the photo that samples it most finely (as :func:`compose_views`' ``best``).

    A coarse ``surface`` (a few hundred pixels across) is enough: the density varies smoothly over it.

    Parameters
    ----------
    camera : the camera of every photo.
    poses : per photo ``(R, C)``, (3, 3) world -> camera rotation and (3,) centre, mm.
    surface : the specimen's raster, any resolution.

    Returns
    -------
    mm per photo pixel; NaN when no photo sees the specimen.
    """
    best = np.zeros(surface.shape, np.float32)
    for R, C in poses:
        depth = photo_depth(surface.mesh, camera, R, C) if surface.mesh is not None else None
        _, _, density = rectification_maps(camera, R, C, surface, slice(None), depth)
        np.maximum(best, density, out=best)
    seen = best > 0
    return float(np.median(1.0 / np.sqrt(best[seen]))) if seen.any() else math.nan


def photo_footprint(camera: Camera, poses: list[tuple[np.ndarray, np.ndarray]], surface: Surface) -> np.ndarray:
    """Each point's photo pixel on the specimen, as the (2, 2) matrix ``F = J^-1 J^-T`` (mm^2), ``J`` the
    Jacobian of photo pixel (u, v) by plane position (x, y) mm, of the photo that samples it most finely
    (as :func:`photo_sampling`).

    ``sqrt(n^T F n)`` is the photo pixel's extent across a line of unit normal ``n`` (mm per photo pixel across
    it: the spread of the pixel's footprint and of an isotropic photo PSF along ``n`` scale by it), and
    ``det(F) ** 0.25`` the isotropic sampling of :func:`photo_sampling`. An oblique view's pixel reaches
    ``1 / sin(elevation)`` times farther along the view than across it, so the same crack can be two photo
    pixels wide across the view and one along it.

    Parameters
    ----------
    camera, poses : as :func:`photo_sampling`.
    surface : the raster to evaluate on; a coarse one (a few hundred pixels across) is enough.

    Returns
    -------
    (H, W, 3) float32 ``(F_xx, F_xy, F_yy)``; zeros where no photo sees the point.
    """
    best = np.zeros(surface.shape, np.float32)
    out = np.zeros((*surface.shape, 3), np.float32)
    points = surface.points().reshape(-1, 3)
    axes = surface.frame.axes
    if surface.flat:
        along = np.broadcast_to(axes[:2].T, (len(points), 3, 2))  # d model point / d (x, y)
    else:  # the surface climbs its slopes along the plane's normal
        dx, dy = (slope.reshape(-1, 1) for slope in surface._slopes)
        along = np.stack([axes[0] + dx * axes[2], axes[1] + dy * axes[2]], axis=-1)
    for R, C in poses:
        depth = photo_depth(surface.mesh, camera, R, C) if surface.mesh is not None else None
        _, _, density = rectification_maps(camera, R, C, surface, slice(None), depth)
        better = (density > best).ravel()
        if not better.any():
            continue
        cam = world_to_camera(points[better], R, C)
        J = camera.project_jacobian(cam) @ R @ along[better]  # (M, 2, 2) photo px per mm
        inverse = np.linalg.inv(J)
        F = inverse @ inverse.transpose(0, 2, 1)
        out.reshape(-1, 3)[better] = np.column_stack([F[:, 0, 0], F[:, 0, 1], F[:, 1, 1]])
        np.maximum(best, density, out=best)
    return out


def resample_raster(
    image: np.ndarray, mask: np.ndarray, mm_per_px: float, shape: tuple[int, int], out_mm_per_px: float
) -> tuple[np.ndarray, np.ndarray]:
    """A rectified raster at ``mm_per_px`` resampled to ``shape`` at ``out_mm_per_px`` on the same plane
    (pixel (col, row) centred on ``(col, row) * mm_per_px`` in both).

    Going coarser, the image is low-passed first (a Gaussian of 0.5 output px, as ``cv2.INTER_AREA`` roughly
    averages) so grain does not alias; going finer, it is interpolated bicubically (no new detail is made).

    Parameters
    ----------
    image : (H, W, 3) or (H, W) uint8.
    mask : (H, W) bool, where the photos see the specimen.
    shape : (rows, cols) of the output.

    Returns
    -------
    (rows, cols[, 3]) uint8 image and (rows, cols) bool mask (nearest).
    """
    if mm_per_px <= 0 or out_mm_per_px <= 0:
        raise ValueError("resolutions must be positive")
    scale = out_mm_per_px / mm_per_px
    if scale > 1.0:
        image = cv2.GaussianBlur(image, (0, 0), 0.5 * math.sqrt(scale * scale - 1.0))
    cols = np.arange(shape[1], dtype=np.float32) * np.float32(scale)
    rows = np.arange(shape[0], dtype=np.float32) * np.float32(scale)
    map_x, map_y = np.meshgrid(cols, rows)
    out = cv2.remap(image, map_x, map_y, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REPLICATE)
    # The nearest input pixel, but never one past the specimen's far edge: both rasters span the same specimen
    # from 0, so that edge is the last output centre, and the input pixel nearest to it may lie just beyond it
    # (unseen: outside the specimen) although the edge itself is seen.
    near_x = np.minimum(np.rint(map_x), np.floor(cols[-1])).astype(np.float32)
    near_y = np.minimum(np.rint(map_y), np.floor(rows[-1])).astype(np.float32)
    seen = cv2.remap(mask.astype(np.uint8), near_x, near_y, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT)
    return out, seen.astype(bool)
