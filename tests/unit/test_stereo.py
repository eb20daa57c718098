"""Stereo rig JSON, midpoint triangulation and measurement uncertainty on a synthetic rig with known truth."""

from __future__ import annotations

import json

import numpy as np
import pytest

from workers.algorithms.calibration import StereoRig, measure, triangulate_midpoint
from workers.algorithms.geometry import Camera, rotation_from_vector, vector_from_rotation

# Two different distorted lenses, one per convention, 150 mm apart and toed in by 3 degrees.
LEFT = Camera(1280, 960, fx=1000.0, fy=1002.0, cx=641.0, cy=478.5, k1=-0.22, k2=0.06, t1=4e-4)
RIGHT = Camera(1280, 960, fx=985.0, fy=984.0, cx=633.0, cy=487.0, k1=0.2, k2=0.02, t2=-3e-4, convention="restore_ideal")
RIG = StereoRig(LEFT, RIGHT, rotation_from_vector(np.radians([0.5, -3.0, 0.2])), np.array([-150.0, 1.5, 3.0]))


def image_pair(rig: StereoRig, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) points in the left camera frame -> their pixels in the left and right images."""
    return rig.left.project(points), rig.right.project(points @ rig.R.T + rig.T)


def scene_points(n: int, seed: int) -> np.ndarray:
    """Points between 0.6 and 3 m in front of the rig, inside both frames."""
    rng = np.random.default_rng(seed)
    z = rng.uniform(600.0, 3000.0, n)
    xy = rng.uniform(-0.45, 0.45, (n, 2)) * z[:, None] * [1.0, 0.75]
    return np.column_stack([xy + [75.0, 0.0], z])


def test_midpoint_triangulation_is_exact_on_noiseless_rays() -> None:
    points = scene_points(500, seed=0)
    left_px, right_px = image_pair(RIG, points)
    assert (left_px.min() > 0) and (right_px.min() > 0) and right_px[:, 0].max() < 1279  # truly in both frames
    found, gap = triangulate_midpoint(RIG, left_px, right_px)
    depth = np.linalg.norm(points, axis=1)
    assert (np.linalg.norm(found - points, axis=1) / depth).max() < 1e-11  # round-off, amplified by Z / B
    assert (gap / depth).max() < 1e-11


def test_midpoint_is_halfway_along_the_common_perpendicular_of_skew_rays() -> None:
    points = scene_points(50, seed=1)
    left_px, right_px = image_pair(RIG, points)
    right_px = right_px + [0.0, 3.0]  # vertical disparity: the rays no longer meet
    found, gap = triangulate_midpoint(RIG, left_px, right_px)
    d_left = np.linalg.norm(np.cross(found, RIG.left.unproject(left_px)), axis=1)
    d_right = np.linalg.norm(np.cross(found - RIG.right_centre, RIG.right.unproject(right_px) @ RIG.R), axis=1)
    assert gap.min() > 0.1  # mm
    assert np.allclose(d_left, gap / 2, rtol=1e-6) and np.allclose(d_right, gap / 2, rtol=1e-6)


def test_a_known_length_is_measured_within_its_reported_uncertainty_under_pixel_noise() -> None:
    rng = np.random.default_rng(2)
    ends = np.array([[-180.0, 40.0, 1500.0], [320.0, -60.0, 1540.0]])  # a 511.5 mm bar, 1.5 m away
    length = float(np.linalg.norm(ends[1] - ends[0]))
    left_px, right_px = image_pair(RIG, ends)
    trials = 300
    noisy_left = np.tile(left_px, (trials, 1)) + rng.normal(0.0, 0.3, (2 * trials, 2))
    noisy_right = np.tile(right_px, (trials, 1)) + rng.normal(0.0, 0.3, (2 * trials, 2))
    found, _ = triangulate_midpoint(RIG, noisy_left, noisy_right)
    errors = np.linalg.norm(found[1::2] - found[0::2], axis=1) - length
    sigma = measure(RIG, left_px, right_px, perturb_px=0.3).distance_sigma[0, 1]
    assert np.abs(errors).max() < 8.0  # mm: 1.6 % (depth error ~ Z^2 / (f B) * disparity error ~ 7 mm per point)
    assert abs(errors.mean()) < 4 * sigma / np.sqrt(trials)  # no bias beyond the noise
    assert 0.85 < errors.std() / sigma < 1.15  # the reported sigma is the observed scatter


def test_reported_uncertainty_grows_with_depth() -> None:
    depths = np.array([500.0, 1000.0, 2000.0, 4000.0])
    points = np.column_stack([np.full(4, 75.0), np.zeros(4), depths])
    bars = np.vstack([points, points + [100.0, 0.0, 0.0]])  # a 100 mm bar at each depth
    result = measure(RIG, *image_pair(RIG, bars), perturb_px=0.5)
    sigma = result.point_sigma[:4]
    assert np.all(np.diff(sigma) > 0)
    assert 10.0 < sigma[3] / sigma[1] < 20.0  # depth error grows as Z^2 / (f B): 16 for 4x the depth
    bar_sigma = result.distance_sigma[np.arange(4), np.arange(4) + 4]
    assert np.all(np.diff(bar_sigma) > 0)
    assert np.allclose(result.distances[np.arange(4), np.arange(4) + 4], 100.0, atol=1e-6)
    assert np.allclose(np.diagonal(result.distances), 0.0) and np.allclose(result.distances, result.distances.T)
    cov = result.point_covariance[0]
    assert np.argmax(np.linalg.eigvalsh(cov)) == 2 and abs(np.linalg.eigh(cov)[1][2, 2]) > 0.99  # along the ray


def test_rig_covariance_is_propagated_like_a_monte_carlo_of_rigs() -> None:
    cov = np.diag([np.radians(0.02) ** 2] * 3 + [0.2**2, 0.1**2, 0.1**2])  # 0.02 deg, 0.1-0.2 mm
    rig = StereoRig(LEFT, RIGHT, RIG.R, RIG.T, cov)
    points = np.array([[-200.0, 50.0, 1200.0], [300.0, -100.0, 2500.0]])
    left_px, right_px = image_pair(RIG, points)
    result = measure(rig, left_px, right_px, perturb_px=0.2)
    plain = measure(RIG, left_px, right_px, perturb_px=0.2)
    assert np.all(plain.point_sigma_rig == 0) and np.allclose(result.point_sigma_px, plain.point_sigma_px)
    assert np.allclose(result.point_sigma, np.hypot(result.point_sigma_px, result.point_sigma_rig))
    rng = np.random.default_rng(3)
    rvec = vector_from_rotation(RIG.R)
    lengths = []
    for draw in rng.multivariate_normal(np.concatenate([rvec, RIG.T]), cov, 400):
        found, _ = triangulate_midpoint(RIG.replace_pose(rotation_from_vector(draw[:3]), draw[3:]), left_px, right_px)
        lengths.append(np.linalg.norm(found[1] - found[0]))
    assert 0.85 < np.std(lengths) / result.distance_sigma_rig[0, 1] < 1.15


def test_rig_json_round_trip() -> None:
    rig = StereoRig(LEFT, RIGHT, RIG.R, RIG.T, np.diag([1e-8] * 3 + [0.01] * 3))
    back = StereoRig.from_json(json.loads(json.dumps(rig.to_json())))
    assert back.left == LEFT and back.right == RIGHT and back.right.convention == "restore_ideal"
    assert np.array_equal(back.R, rig.R) and np.array_equal(back.T, rig.T)
    assert back.covariance is not None and rig.covariance is not None
    assert np.array_equal(back.covariance, rig.covariance)
    assert StereoRig.from_json({**rig.to_json(), "covariance": None}).covariance is None
    assert abs(back.baseline - np.linalg.norm(RIG.T)) < 1e-12


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"R": np.diag([1.0, 1.0, -1.0]).tolist()}, "R must be a rotation matrix"),
        ({"R": [[1, 0], [0, 1]]}, r"R must be finite numbers of shape \(3, 3\)"),
        ({"T": [0.0, 0.0, 0.0]}, "T must be non-zero"),
        ({"T": [1.0, "a", 2.0]}, "T must be numbers"),
        ({"T": [1.0, float("nan"), 2.0]}, "T must be finite"),
        ({"covariance": np.eye(5).tolist()}, r"covariance must be finite numbers of shape \(6, 6\)"),
        ({"covariance": (np.eye(6) - 2 * np.eye(6)).tolist()}, "non-negative diagonal"),
        ({"left": {"width": 10}}, "camera"),
    ],
)
def test_rig_from_json_rejects_bad_input(change: dict, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        StereoRig.from_json({**RIG.to_json(), **change})


def test_rig_from_json_names_missing_parts() -> None:
    with pytest.raises(ValueError, match="missing R, T"):
        StereoRig.from_json({"left": LEFT.to_json(), "right": RIGHT.to_json()})
    with pytest.raises(ValueError, match="must be a JSON object"):
        StereoRig.from_json([1, 2])  # type: ignore[arg-type]


def test_triangulation_and_measure_reject_misuse() -> None:
    px = np.zeros((3, 2))
    with pytest.raises(ValueError, match="left_px has 3 points but right_px has 2"):
        triangulate_midpoint(RIG, px, px[:2])
    with pytest.raises(ValueError, match=r"right_px must be finite \(N, 2\)"):
        triangulate_midpoint(RIG, px, np.zeros((3, 3)))
    with pytest.raises(ValueError, match="perturb_px must be a positive number"):
        measure(RIG, px, px, perturb_px=0.0)
