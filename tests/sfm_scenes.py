"""Synthetic structure-from-motion scenes with known truth, for tracks, bundle adjustment and
reconstruction tests.

A scene is a ring of oblique cameras around, and a smaller ring of nadir cameras above, a ground with
relief (two superposed waves, +-6 m). Ground points are projected through a Brown-distorted pinhole
camera (OpenCV convention, ``distort_ideal``); each camera "detects" 80 % of the points it sees, with
Gaussian pixel noise of ``noise_px`` RMS (2D length: per-axis sigma ``noise_px / sqrt(2)``). Pairs of
frames that see enough common points and look in similar directions are matched, and a fraction
``outlier_fraction`` of every pair's matches is redirected to a wrong feature of the second frame.

World frame: east, north, up metres (the local frame of a GPS job); camera pose ``X_cam = R (X - C)``.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from workers.algorithms.geometry import Camera, rotation_from_vector

TRUE_CAMERA = Camera(width=1200, height=900, fx=1000.0, fy=1000.0, cx=603.0, cy=447.5, k1=-0.08, k2=0.02)


@dataclass(frozen=True)
class SfmScene:
    """Truth and measurements.

    Attributes
    ----------
    camera : the true camera, shared by all frames.
    rotations : (F, 3, 3) world -> camera rotations.
    centres : (F, 3) camera centres, metres.
    points : (P, 3) ground points, metres.
    features : per frame (N_i, 2) float64 observed pixel (x, y), in random order.
    feature_point : per frame (N_i,) int64 index of the true point of each feature.
    matches : (i, j) -> (features of i, features of j) index arrays, wrong matches included.
    wrong : (i, j) -> (M,) bool, True for the planted wrong matches.
    attitude : (F, 3) DJI gimbal yaw, pitch, roll degrees, computed from the truth geometrically.
    size : metres, the diagonal of the box holding cameras and points.
    """

    camera: Camera
    rotations: np.ndarray
    centres: np.ndarray
    points: np.ndarray
    features: list[np.ndarray]
    feature_point: list[np.ndarray]
    matches: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]]
    wrong: dict[tuple[int, int], np.ndarray]
    attitude: np.ndarray
    size: float

    def project(self, frame: int, world: np.ndarray) -> np.ndarray:
        """(N, 3) world points -> (N, 2) true pixels in ``frame`` (noise-free)."""
        cam = (np.asarray(world, dtype=np.float64).reshape(-1, 3) - self.centres[frame]) @ self.rotations[frame].T
        return self.camera.project(cam)


def ground_height(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Relief of the synthetic ground, metres."""
    return 4.0 * np.sin(x / 15.0) * np.cos(y / 20.0) + 2.0 * np.sin((x + y) / 9.0)


def look_at(centre: np.ndarray, target: np.ndarray, up_hint: np.ndarray = np.array([0.0, 0.0, 1.0])) -> np.ndarray:
    """World -> camera rotation of a camera at ``centre`` looking at ``target`` with a level x axis
    (no roll); ``up_hint`` decides the image-up direction when looking straight down."""
    z = target - centre
    z = z / np.linalg.norm(z)
    x = np.cross(z, up_hint)
    if np.linalg.norm(x) < 1e-9:
        raise ValueError("up_hint is parallel to the viewing direction")
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(z, x), z])


def nadir(heading_deg: float) -> np.ndarray:
    """World -> camera rotation looking straight down with the image top towards ``heading_deg``
    (clockwise from north)."""
    h = np.radians(heading_deg)
    top = np.array([np.sin(h), np.cos(h), 0.0])
    return np.stack([np.cross(top, [0.0, 0.0, 1.0]), -top, [0.0, 0.0, -1.0]])


def attitude_of(R: np.ndarray) -> tuple[float, float, float]:
    """DJI gimbal (yaw, pitch, roll) degrees of a no-roll camera, read off its axes: yaw = heading of
    the optical axis (of the image top when the axis is vertical), pitch = elevation of the axis."""
    z, y = R[2], R[1]
    pitch = np.degrees(np.arcsin(np.clip(z[2], -1, 1)))
    heading = z if np.hypot(z[0], z[1]) > 1e-6 else -y
    return float(np.degrees(np.arctan2(heading[0], heading[1]))), float(pitch), 0.0


def make_sfm_scene(
    n_ring: int = 16,
    n_nadir: int = 8,
    n_points: int = 2500,
    noise_px: float = 0.5,
    outlier_fraction: float = 0.1,
    seed: int = 0,
) -> SfmScene:
    """A seeded scene; see the module docstring."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(-45.0, 45.0, (n_points, 2))
    points = np.column_stack([xy, ground_height(xy[:, 0], xy[:, 1])])
    rotations, centres = _camera_rig(n_ring, n_nadir, rng)
    return _observe(rotations, centres, points, noise_px, outlier_fraction, rng)


def _camera_rig(n_ring: int, n_nadir: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    rotations, centres = [], []
    for k in range(n_ring):  # oblique, about 37 degrees below the horizon, looking at the middle
        a = 2 * np.pi * k / n_ring
        C = np.array([60.0 * np.cos(a), 60.0 * np.sin(a), 45.0]) + rng.normal(0, 1.0, 3)
        rotations.append(look_at(C, rng.normal(0, 3.0, 3) * [1, 1, 0]))
        centres.append(C)
    for k in range(n_nadir):
        a = 2 * np.pi * (k + 0.5) / n_nadir
        centres.append(np.array([25.0 * np.cos(a), 25.0 * np.sin(a), 60.0]) + rng.normal(0, 1.0, 3))
        rotations.append(nadir(np.degrees(a) + 90.0))
    return np.array(rotations), np.array(centres)


def _matches(
    rotations: np.ndarray, feature_point: list[np.ndarray], outlier_fraction: float, rng: np.random.Generator
) -> tuple[dict, dict]:
    matches, wrong = {}, {}
    n = len(rotations)
    for i in range(n):
        for j in range(i + 1, n):
            if rotations[i][2] @ rotations[j][2] < np.cos(np.radians(70.0)):
                continue  # views too different for a feature matcher
            common, fi, fj = np.intersect1d(feature_point[i], feature_point[j], return_indices=True)
            if len(common) < 30:
                continue
            bad = rng.random(len(fi)) < outlier_fraction
            fj = fj.copy()
            fj[bad] = (fj[bad] + rng.integers(1, len(feature_point[j]), bad.sum())) % len(feature_point[j])
            order = rng.permutation(len(fi))
            matches[(i, j)] = (fi[order].astype(np.int64), fj[order].astype(np.int64))
            wrong[(i, j)] = bad[order]
    return matches, wrong


def similarity_align(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Least-squares ``dst ~ s R src + t`` in 3D (Umeyama 1991); (s, R (3, 3), t (3,))."""
    mu_s, mu_d = src.mean(axis=0), dst.mean(axis=0)
    a, b = src - mu_s, dst - mu_d
    U, S, Vt = np.linalg.svd(b.T @ a / len(src))
    d = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    R = U @ d @ Vt
    s = float(np.trace(np.diag(S) @ d) / ((a**2).sum() / len(src)))
    return s, R, mu_d - s * R @ mu_s


def make_strip_scene(
    strips: int = 2,
    per_strip: int = 6,
    heading_deg: float = 40.0,
    altitude_m: float = 60.0,
    spacing_m: float = 14.0,
    strip_gap_m: float = 30.0,
    n_points: int = 3000,
    noise_px: float = 0.5,
    outlier_fraction: float = 0.1,
    turn_last_deg: float = 0.0,
    seed: int = 0,
) -> SfmScene:
    """Parallel strips of nadir frames flown back and forth (a survey grid): the image top faces the direction
    of flight, so consecutive strips are turned by 180 degrees. Strip ``s`` runs along ``heading_deg`` (even
    ``s``) or against it, ``strip_gap_m`` beside the previous one; frames ``spacing_m`` apart, with a few
    degrees of attitude noise and a metre of height wobble. The last frame of each strip is turned by
    ``turn_last_deg`` more (the drone turning at the strip's end)."""
    rng = np.random.default_rng(seed)
    h = np.radians(heading_deg)
    along, across = np.array([np.sin(h), np.cos(h), 0.0]), np.array([np.cos(h), -np.sin(h), 0.0])
    rotations, centres = [], []
    for s in range(strips):
        steps = range(per_strip) if s % 2 == 0 else reversed(range(per_strip))
        for k in steps:
            offset = (k - (per_strip - 1) / 2) * spacing_m * along + (s - (strips - 1) / 2) * strip_gap_m * across
            centres.append(offset + [0.0, 0.0, altitude_m] + rng.normal(0, [0.3, 0.3, 1.0]))
            tilt = rotation_from_vector(np.radians(rng.normal(0, 1.5, 3)))
            turn = turn_last_deg if k == (per_strip - 1 if s % 2 == 0 else 0) else 0.0
            rotations.append(tilt @ nadir(heading_deg + (0.0 if s % 2 == 0 else 180.0) + turn + rng.normal(0, 3.0)))
    extent = np.abs(np.array(centres)[:, :2]).max() + altitude_m
    xy = rng.uniform(-extent, extent, (n_points, 2))
    points = np.column_stack([xy, ground_height(xy[:, 0], xy[:, 1])])
    scene = _observe(np.array(rotations), np.array(centres), points, noise_px, outlier_fraction, rng)
    return replace(scene, attitude=np.array([dji_attitude(R) for R in scene.rotations]))


def dji_attitude(R: np.ndarray) -> tuple[float, float, float]:
    """DJI gimbal (yaw, pitch, roll) degrees of any world -> camera rotation: the exact inverse of
    ``rotation_from_attitude`` (camera to world = Rz(-yaw) Rx(pitch) Ry(roll) of a level camera looking north),
    also for tilted frames (near nadir, yaw and roll share the turn about the vertical)."""
    level_north = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
    M = R.T @ level_north.T  # = Rz(a) Rx(pitch) Ry(roll), a = -yaw
    pitch = np.arcsin(np.clip(M[2, 1], -1.0, 1.0))
    roll = np.arctan2(-M[2, 0], M[2, 2])
    a = np.arctan2(-M[0, 1], M[1, 1])
    return float(np.degrees(-a)), float(np.degrees(pitch)), float(np.degrees(roll))


def _observe(
    rotations: np.ndarray,
    centres: np.ndarray,
    points: np.ndarray,
    noise_px: float,
    outlier_fraction: float,
    rng: np.random.Generator,
) -> SfmScene:
    features, feature_point = [], []
    for R, C in zip(rotations, centres, strict=True):
        cam = (points - C) @ R.T
        px = TRUE_CAMERA.project(cam)
        seen = (cam[:, 2] > 1.0) & np.all((px > 5) & (px < [TRUE_CAMERA.width - 6, TRUE_CAMERA.height - 6]), axis=1)
        ids = rng.permutation(np.flatnonzero(seen & (rng.random(len(points)) < 0.8)))
        features.append(px[ids] + rng.normal(0.0, noise_px / np.sqrt(2.0), (len(ids), 2)))
        feature_point.append(ids.astype(np.int64))
    matches, wrong = _matches(rotations, feature_point, outlier_fraction, rng)
    box = np.vstack([points, centres])
    size = float(np.linalg.norm(box.max(axis=0) - box.min(axis=0)))
    attitude = np.array([attitude_of(R) for R in rotations])
    return SfmScene(TRUE_CAMERA, rotations, centres, points, features, feature_point, matches, wrong, attitude, size)
