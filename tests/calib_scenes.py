"""Synthetic calibration scenes with known truth: lenses, target poses, stereo rigs, straight lines and
rendered chessboards. Everything is seeded; noise is Gaussian per pixel coordinate.

Pixel convention: OpenCV's (integer coordinates at pixel centres); poses ``X_cam = R @ (X - C)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from workers.algorithms.calibration import board_points
from workers.algorithms.geometry import Camera, rotation_from_vector, world_to_camera

# A wide-angle lens with strong barrel distortion: 1.4 px of tangential and ~140 px of radial
# displacement at the frame corners.
LENS = Camera(1280, 960, fx=1000.0, fy=1004.0, cx=643.2, cy=478.9, k1=-0.28, k2=0.09, k3=-0.01, t1=6e-4, t2=-4e-4)
LENS_RESTORE = LENS.with_convention("restore_ideal")  # the same kind of lens, specified as a correction


@dataclass(frozen=True)
class BoardScene:
    """Views of a planar target by one camera.

    views : list of (object points (N_v, 3), observed pixels (N_v, 2)); only points inside the frame.
    truth_px : list of (N_v, 2) noiseless pixels.
    rotations, centres : (V, 3, 3), (V, 3) true camera poses in the target frame.
    """

    views: list[tuple[np.ndarray, np.ndarray]]
    truth_px: list[np.ndarray]
    rotations: np.ndarray
    centres: np.ndarray


def look_at(centre: np.ndarray, target: np.ndarray, roll: float) -> np.ndarray:
    """Rotation (3, 3) of a camera at ``centre`` looking at ``target`` (z forward, y down), rolled by ``roll`` rad."""
    z = (target - centre) / np.linalg.norm(target - centre)
    up = np.array([0.0, 1.0, 0.0]) if abs(z[1]) < 0.9 else np.array([1.0, 0.0, 0.0])
    x = np.cross(up, z)
    x /= np.linalg.norm(x)
    R = np.stack([x, np.cross(z, x), z])
    return rotation_from_vector(np.array([0.0, 0.0, roll])) @ R


def rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The smallest rotation (3, 3) taking unit vector ``a`` to unit vector ``b``."""
    axis = np.cross(a, b)
    angle = np.arctan2(np.linalg.norm(axis), a @ b)
    return rotation_from_vector(axis / max(np.linalg.norm(axis), 1e-300) * angle)


def random_poses(
    camera: Camera,
    aims_px: np.ndarray,
    rng: np.random.Generator,
    board_size: tuple[float, float],
    distance: tuple[float, float],
    max_tilt_deg: float = 50.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Camera poses (R (n, 3, 3), C (n, 3)) looking at a board in the plane Z = 0 from Z < 0.

    View k sits at a random ``distance`` from a random point of the board, 10 .. ``max_tilt_deg`` off the
    board normal, rolled at random, and turned so that point is seen at pixel ``aims_px[k]``: aiming
    views at the corners and edges covers the whole frame, as a careful calibration does.
    """
    rotations, centres = [], []
    w, h = board_size
    for aim in np.asarray(aims_px, dtype=np.float64):
        target = np.array([rng.uniform(0.3, 0.7) * w, rng.uniform(0.3, 0.7) * h, 0.0])
        tilt, azimuth = np.radians(rng.uniform(10.0, max_tilt_deg)), rng.uniform(0.0, 2 * np.pi)
        direction = np.array([np.sin(tilt) * np.cos(azimuth), np.sin(tilt) * np.sin(azimuth), -np.cos(tilt)])
        centre = target + rng.uniform(*distance) * direction
        turn = rotation_between(np.array([0.0, 0.0, 1.0]), camera.unproject(aim[None])[0])
        rotations.append(turn @ look_at(centre, target, rng.uniform(-0.6, 0.6)))
        centres.append(centre)
    return np.array(rotations), np.array(centres)


def frame_aims(camera: Camera, n: int, rng: np.random.Generator) -> np.ndarray:
    """(n, 2) pixels to aim views at: the four corners and four edge middles (inset by 15 %), then random."""
    fx, fy = np.meshgrid([0.15, 0.5, 0.85], [0.15, 0.5, 0.85])
    ring = np.stack([fx.ravel(), fy.ravel()], axis=1)[[0, 2, 6, 8, 1, 3, 5, 7]]
    fractions = np.vstack([ring, rng.uniform(0.25, 0.75, (max(n - len(ring), 0), 2))])[:n]
    return fractions * [camera.width - 1, camera.height - 1]


def visible(camera: Camera, points_cam: np.ndarray, margin: float = 2.0) -> np.ndarray:
    """(N,) bool: in front of the camera, inside the frame with ``margin`` px to spare, and inside the
    field of view: a Brown polynomial folds over far outside the frame and would otherwise project
    points from behind the lens's field into the image."""
    px = camera.project(points_cam)
    inside = (px[:, 0] > margin) & (px[:, 0] < camera.width - 1 - margin)
    inside &= (px[:, 1] > margin) & (px[:, 1] < camera.height - 1 - margin)
    corners = np.array([[0, 0], [camera.width - 1, 0], [0, camera.height - 1], [camera.width - 1, camera.height - 1]])
    field = np.linalg.norm(camera.pixel_to_normalised(corners), axis=1).max()
    with np.errstate(divide="ignore", invalid="ignore"):
        radius = np.linalg.norm(points_cam[:, :2] / points_cam[:, 2:3], axis=1)
    return inside & (points_cam[:, 2] > 0) & (radius <= field)


def board_scene(
    camera: Camera = LENS,
    n_views: int = 15,
    noise_px: float = 0.2,
    seed: int = 0,
    pattern: tuple[int, int] = (17, 12),
    square: float = 40.0,
) -> BoardScene:
    """A large board (17 x 12 corners of 40 mm) in ``n_views`` poses that cover the whole frame between them."""
    rng = np.random.default_rng(seed)
    obj = board_points(pattern, square)
    size = ((pattern[0] - 1) * square, (pattern[1] - 1) * square)
    rotations, centres = random_poses(camera, frame_aims(camera, n_views, rng), rng, size, distance=(480.0, 750.0))
    views, truth = [], []
    for R, C in zip(rotations, centres, strict=True):
        cam_pts = world_to_camera(obj, R, C)
        keep = visible(camera, cam_pts)
        px = camera.project(cam_pts[keep])
        views.append((obj[keep], px + rng.normal(0.0, noise_px, px.shape)))
        truth.append(px)
    return BoardScene(views, truth, rotations, centres)


@dataclass(frozen=True)
class StereoScene:
    """Views of a target by a rig with ``X_right = R @ X_left + T``; only points seen by both cameras."""

    left: Camera
    right: Camera
    R: np.ndarray
    T: np.ndarray
    views: list[tuple[np.ndarray, np.ndarray, np.ndarray]]


RIG_R = rotation_from_vector(np.radians([0.8, -6.0, 0.5]))  # toed in by 6 degrees
RIG_T = np.array([-150.0, 2.0, 5.0])  # mm: the right camera 150 mm to the right


def stereo_scene(n_views: int = 10, noise_px: float = 0.2, seed: int = 1) -> StereoScene:
    """A 150 mm rig of two different lenses (one per convention) over an 11 x 8 board of 40 mm squares,
    wholly seen by both cameras in every view (as a stereo chessboard detector requires)."""
    rng = np.random.default_rng(seed)
    left = LENS
    right = Camera(
        1280, 960, fx=980.0, fy=982.0, cx=630.0, cy=490.0, k1=0.25, k2=0.05, t1=-3e-4, convention="restore_ideal"
    )
    obj = board_points((11, 8), 40.0)
    views: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
    while len(views) < n_views:
        aim = rng.uniform(0.25, 0.75, (1, 2)) * [left.width, left.height]
        rotations, centres = random_poses(left, aim, rng, (400.0, 280.0), distance=(600.0, 1000.0))
        in_left = world_to_camera(obj, rotations[0], centres[0])
        in_right = in_left @ RIG_R.T + RIG_T
        if visible(left, in_left).all() and visible(right, in_right).all():
            lpx, rpx = left.project(in_left), right.project(in_right)
            views.append((obj, lpx + rng.normal(0, noise_px, lpx.shape), rpx + rng.normal(0, noise_px, rpx.shape)))
    return StereoScene(left, right, RIG_R, RIG_T, views)


def straight_lines(
    camera: Camera, n_lines: int = 24, n_points: int = 40, noise_px: float = 0.1, seed: int = 2
) -> list[np.ndarray]:
    """Images of straight 3-D lines (random directions across the whole field) through ``camera``."""
    rng = np.random.default_rng(seed)
    lines: list[np.ndarray] = []
    while len(lines) < n_lines:
        a, b = (np.append(rng.uniform(-0.75, 0.75, 2) * [1.0, 0.72], 1.0) * rng.uniform(2.0, 5.0) for _ in (0, 1))
        seg = a + np.linspace(0.0, 1.0, 4 * n_points)[:, None] * (b - a)
        keep = visible(camera, seg)
        if keep.sum() >= n_points // 2:
            px = camera.project(seg[keep][:: max(1, keep.sum() // n_points)])
            lines.append(px + rng.normal(0.0, noise_px, px.shape))
    return lines


def mapping_error_px(estimate: Camera, truth: Camera, grid: int = 25) -> float:
    """Largest pixel disagreement over the frame: truth's ray through each grid pixel, projected by ``estimate``."""
    u, v = np.meshgrid(np.linspace(0, truth.width - 1, grid), np.linspace(0, truth.height - 1, grid))
    uv = np.stack([u.ravel(), v.ravel()], axis=1)
    return float(np.linalg.norm(estimate.normalised_to_pixel(truth.pixel_to_normalised(uv)) - uv, axis=1).max())


def render_chessboard(
    pattern: tuple[int, int], square_px: int, H: np.ndarray, size: tuple[int, int]
) -> tuple[np.ndarray, np.ndarray]:
    """A chessboard image warped by the homography ``H`` (board canvas px -> image px), and the true
    image positions (N, 2) of its inner corners in OpenCV's order.

    The canvas has a one-square white margin; square k spans canvas pixels k*s .. (k+1)*s - 1, so
    an inner corner lies on a pixel boundary (half-integer coordinate).
    """
    cols, rows = pattern
    squares = np.indices((rows + 1, cols + 1)).sum(axis=0) % 2
    board = np.kron(squares, np.ones((square_px, square_px))) * 255
    canvas = np.pad(255 - board, square_px, constant_values=255).astype(np.float32)
    blurred = cv2.GaussianBlur(canvas, (0, 0), 1.0)  # a lens's blur, and no aliasing when H shrinks the board
    image = cv2.warpPerspective(blurred, H, size, flags=cv2.INTER_LINEAR, borderValue=255.0)
    image = np.clip(np.rint(image), 0, 255).astype(np.uint8)
    j, i = np.mgrid[1 : rows + 1, 1 : cols + 1]
    corners = np.stack([i.ravel(), j.ravel()], axis=1) * square_px + square_px - 0.5
    mapped = np.c_[corners, np.ones(len(corners))] @ H.T
    return image, mapped[:, :2] / mapped[:, 2:]
