"""Dense stereo between neighbouring posed frames of a flight: which pairs overlap enough, their calibrated
rectification from the adjusted cameras, and their disparities back to ground points.

A pair is rectified by one rotation shared by both views (Fusiello, Trucco & Verri 2000, "A compact algorithm
for rectification of stereo pairs"): its x axis runs along the baseline from the left camera to the right one,
its z axis is the mean of both optical axes made square to it. Scene points then lie on one row of both views
whatever way the flight ran across the photos (``cv2.stereoRectify`` turns a baseline along the photos' columns
into rectified columns, which a row matcher cannot use). The views are rendered through the adjusted camera
with its distortion, at a reduced focal length so matching stays fast, and each is shifted so the ground both
frames see fills its canvas. Disparity is ``d = x_left - x_right`` in rectified pixels, as in the rest of the
domain.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from workers.algorithms.geometry import Camera

Pose = tuple[np.ndarray, np.ndarray]  # (R (3, 3), C (3,)): X_cam = R (X - C)
MIN_OVERLAP = 0.3  # a pair whose frames share less than this share of their ground is not matched
MIN_BASE_RATIO = 0.05  # ... nor one whose baseline is under this share of the height above the ground
PAIRS_PER_FRAME = 2  # each frame is matched with at most this many partners, those it overlaps most
CANVAS_MARGIN_PX = 16  # rectified canvases reach this far past the ground both frames see
MAX_CANVAS_GROWTH = 4.0  # a canvas this many times a reduced frame's area means an oblique, broken geometry
MAP_STEP_PX = 8  # rectification maps are traced at nodes this far apart and interpolated between
OVERLAP_SAMPLES = (16, 12)  # pixels of a frame traced to the ground to measure its overlap, across and down


def overlap_share(camera: Camera, a: Pose, b: Pose, z: float) -> float:
    """Share of frame ``a``'s ground (the plane ``Z = z``) that frame ``b`` sees too, from a grid of pixels."""
    ground = ground_samples(camera, a, z)
    if len(ground) == 0:
        return 0.0
    return float(_seen(camera, b, ground).sum()) / (OVERLAP_SAMPLES[0] * OVERLAP_SAMPLES[1])


def neighbour_pairs(camera: Camera, poses: dict[int, Pose], z: float) -> list[tuple[int, int]]:
    """Pairs ``(i, j)``, i < j, worth dense matching: sharing at least ``MIN_OVERLAP`` of their ground (both ways,
    averaged), the baseline at least ``MIN_BASE_RATIO`` of the height, each frame with its ``PAIRS_PER_FRAME``
    partners of largest overlap. Sorted."""
    keys = sorted(poses)
    centres = np.array([poses[k][1] for k in keys]).reshape(-1, 3)
    # frames farther apart than two footprints' diagonals (a generous bound, for tilted views) share no ground:
    # only the rest are traced, so a long flight is not N^2 traces
    reach = 2.0 * np.hypot(camera.width, camera.height) / camera.fx * np.maximum(centres[:, 2] - z, 0.0)
    gaps = np.linalg.norm(centres[:, None, :2] - centres[None, :, :2], axis=2)
    scores: dict[tuple[int, int], float] = {}
    for n, i in enumerate(keys):
        for m in np.nonzero(gaps[n, n + 1 :] <= np.maximum(reach[n], reach[n + 1 :]))[0] + n + 1:
            j = keys[m]
            (_, ci), (_, cj) = poses[i], poses[j]
            height = 0.5 * (ci[2] + cj[2]) - z
            if height <= 0 or np.linalg.norm(cj - ci) < MIN_BASE_RATIO * height:
                continue
            share = 0.5 * (overlap_share(camera, poses[i], poses[j], z) + overlap_share(camera, poses[j], poses[i], z))
            if share >= MIN_OVERLAP:
                scores[(i, j)] = share
    chosen: set[tuple[int, int]] = set()
    for k in keys:
        mine = sorted((s, p) for p, s in scores.items() if k in p)[::-1][:PAIRS_PER_FRAME]
        chosen.update(p for _, p in mine)
    return sorted(chosen)


def view_counts(camera: Camera, poses: dict[int, Pose], points: np.ndarray) -> np.ndarray:
    """(N,) int: how many of the posed frames see each world point (N, 3) inside their frame."""
    counts = np.zeros(len(points), np.int64)
    for pose in poses.values():
        counts += _seen(camera, pose, np.asarray(points, np.float64))
    return counts


def ground_samples(camera: Camera, pose: Pose, z: float) -> np.ndarray:
    """(M, 3) points of the plane ``Z = z`` seen at a grid of the frame's pixels (rays that meet it in front):
    its footprint."""
    R, C = pose
    u, v = np.meshgrid(
        np.linspace(0, camera.width - 1, OVERLAP_SAMPLES[0]), np.linspace(0, camera.height - 1, OVERLAP_SAMPLES[1])
    )
    rays = camera.unproject(np.column_stack([u.ravel(), v.ravel()])) @ R  # R.T @ ray for each row
    down = rays[:, 2] < -1e-9
    t = (z - C[2]) / rays[down, 2]
    return np.asarray(C + t[:, None] * rays[down])


def _seen(camera: Camera, pose: Pose, points: np.ndarray) -> np.ndarray:
    """(M,) bool: the points in front of the camera that land inside its frame."""
    R, C = pose
    cam = (points - C) @ R.T
    front = cam[:, 2] > 1e-9
    px = camera.project(np.where(front[:, None], cam, [0.0, 0.0, 1.0]))
    return np.asarray(front & camera.in_frame(px))


@dataclass(frozen=True, eq=False)
class PosedPair:
    """Two posed frames rectified by one shared rotation.

    ``rotation`` (3, 3) world -> rectified camera frame (both views); ``left_centre``, ``right_centre`` (3,) the
    cameras, the right one on the rectified +x axis; ``focal`` px of both views; ``cx`` (left, right) and ``cy``
    their principal points on ``width`` x ``height`` canvases.
    """

    rotation: np.ndarray
    left_centre: np.ndarray
    right_centre: np.ndarray
    focal: float
    cx: tuple[float, float]
    cy: float
    width: int
    height: int

    @property
    def baseline(self) -> float:
        return float(np.linalg.norm(self.right_centre - self.left_centre))

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """World points (N, 3) -> left (N, 2) and right (N, 2) rectified pixels, and (N,) bool: in front."""
        out = []
        for centre, cx in ((self.left_centre, self.cx[0]), (self.right_centre, self.cx[1])):
            p = (np.asarray(points, np.float64) - centre) @ self.rotation.T
            z = np.where(p[:, 2] > 1e-9, p[:, 2], np.nan)
            out.append(np.column_stack([self.focal * p[:, 0] / z + cx, self.focal * p[:, 1] / z + self.cy]))
        front = np.isfinite(out[0]).all(axis=1)
        return out[0], out[1], front

    def maps(self, camera: Camera, rotation: np.ndarray, side: str) -> tuple[np.ndarray, np.ndarray]:
        """``cv2.remap`` maps (height, width) float32 that render ``side``'s ("left" or "right") photo, taken by
        ``camera`` (with its distortion, at the photo's scale) with world -> camera ``rotation``, as its view."""
        cx = self.cx[0] if side == "left" else self.cx[1]
        # traced at nodes every MAP_STEP_PX and interpolated bilinearly between them: the map is smooth (a
        # rotation and the lens): within 0.013 px in the unit test (k1 -0.05), at a sixth of the cost
        across, down = _nodes(self.width), _nodes(self.height)
        u, v = np.meshgrid(across, down)
        rays = np.column_stack([(u.ravel() - cx) / self.focal, (v.ravel() - self.cy) / self.focal, np.ones(u.size)])
        cam = rays @ (rotation @ self.rotation.T).T  # rectified -> world -> the photo's camera
        front = cam[:, 2] > 1e-9
        px = np.full((u.size, 2), -1e6)
        px[front] = camera.project(cam[front])
        rows, cols = _linear(down, self.height), _linear(across, self.width)
        return tuple(  # type: ignore[return-value]
            (rows @ px[:, k].reshape(u.shape) @ cols.T).astype(np.float32) for k in (0, 1)
        )

    def triangulate(self, cols: np.ndarray, rows: np.ndarray, disparity: np.ndarray) -> np.ndarray:
        """World points (N, 3) of left-view pixels (N,) with their disparities (N,) px; NaN rows where the
        disparity puts the point at or behind the cameras.

        With the right camera at ``baseline`` along x, d = f B / Z + cx_left - cx_right.
        """
        shifted = np.asarray(disparity, np.float64) - (self.cx[0] - self.cx[1])
        depth = np.where(shifted > 1e-6, self.focal * self.baseline / np.maximum(shifted, 1e-6), np.nan)
        x = (np.asarray(cols, np.float64) - self.cx[0]) * depth / self.focal
        y = (np.asarray(rows, np.float64) - self.cy) * depth / self.focal
        return np.asarray(self.left_centre + np.column_stack([x, y, depth]) @ self.rotation)


def _nodes(size: int) -> np.ndarray:
    """Node positions 0, MAP_STEP_PX, ... reaching the last pixel, size - 1."""
    return np.arange(0, size - 1 + MAP_STEP_PX, MAP_STEP_PX, dtype=np.float64)


def _linear(nodes: np.ndarray, size: int) -> np.ndarray:
    """(size, len(nodes)) weights of linear interpolation between the nodes at pixels 0 .. size - 1."""
    x = np.arange(size, dtype=np.float64)
    k = np.minimum(np.floor(x / MAP_STEP_PX).astype(np.int64), len(nodes) - 2)
    t = (x - nodes[k]) / MAP_STEP_PX
    weights = np.zeros((size, len(nodes)))
    weights[np.arange(size), k] = 1.0 - t
    weights[np.arange(size), k + 1] = t
    return weights


def posed_pair(camera: Camera, left: Pose, right: Pose, z: float, focal: float) -> PosedPair | None:
    """The rectification of two posed frames whose ground is near the plane ``Z = z``, at ``focal`` px.

    The canvases cover the ground of the left frame that the right one sees too (their grids of pixels traced
    to the plane), with ``CANVAS_MARGIN_PX`` around it for relief. None when they share no ground, or when
    the canvas would exceed ``MAX_CANVAS_GROWTH`` times the frame at that focal (a view near the horizon).
    """
    (r_l, c_l), (r_r, c_r) = left, right
    x_axis = (c_r - c_l) / np.linalg.norm(c_r - c_l)
    z_axis = r_l[2] + r_r[2]  # the optical axes in the world (the third rows of world -> camera)
    z_axis = z_axis - np.dot(z_axis, x_axis) * x_axis
    z_axis /= np.linalg.norm(z_axis)
    rotation = np.stack([x_axis, np.cross(z_axis, x_axis), z_axis])
    ground = ground_samples(camera, left, z)
    ground = ground[_seen(camera, right, ground)]
    if len(ground) < 4:
        return None
    draft = PosedPair(rotation, c_l, c_r, focal, (0.0, 0.0), 0.0, 0, 0)
    left_px, right_px, front = draft.project(ground)
    if not front.all():
        return None
    m = CANVAS_MARGIN_PX
    lo_l, lo_r = left_px.min(axis=0), right_px.min(axis=0)
    width = int(np.ceil(max(np.ptp(left_px[:, 0]), np.ptp(right_px[:, 0])))) + 2 * m + 1
    height = int(np.ceil(np.ptp(left_px[:, 1]))) + 2 * m + 1
    scale = focal / camera.fx
    if width * height > MAX_CANVAS_GROWTH * camera.width * camera.height * scale**2:
        return None
    return PosedPair(rotation, c_l, c_r, focal, (m - lo_l[0], m - lo_r[0]), m - lo_l[1], width, height)


def reduced_view(image: np.ndarray, camera: Camera, scale: float) -> tuple[np.ndarray, Camera]:
    """The photo and its camera at ``scale`` (< 1: area-averaged, so the matcher sees no aliasing); the
    distortion acts on normalised coordinates, so only the matrix scales (pixel centres stay centres)."""
    if scale >= 1.0:
        return image, camera
    h, w = image.shape[:2]
    size = (max(1, round(w * scale)), max(1, round(h * scale)))
    small = cv2.resize(image, size, interpolation=cv2.INTER_AREA)
    sx, sy = size[0] / w, size[1] / h
    return small, camera.replace(
        width=size[0],
        height=size[1],
        fx=camera.fx * sx,
        fy=camera.fy * sy,
        cx=(camera.cx + 0.5) * sx - 0.5,
        cy=(camera.cy + 0.5) * sy - 0.5,
    )
