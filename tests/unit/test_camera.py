"""The camera model against OpenCV and against itself: both conventions, conversions, Jacobians, JSON."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from workers.algorithms.geometry import Camera, rotation_from_vector, vector_from_rotation, world_to_camera

# A wide-angle lens with clearly visible barrel distortion (about 40 px at the corners of 2008x1336).
LENS = dict(
    width=2008, height=1336, fx=1450.0, fy=1452.0, cx=1010.3, cy=661.8, k1=-0.21, k2=0.09, k3=-0.015, t1=6e-4, t2=-4e-4
)


def frame_pixels(cam: Camera, n: int = 33) -> np.ndarray:
    u, v = np.meshgrid(np.linspace(0, cam.width - 1, n), np.linspace(0, cam.height - 1, n))
    return np.stack([u.ravel(), v.ravel()], axis=1)


@pytest.mark.parametrize("convention", ["distort_ideal", "restore_ideal"])
def test_round_trip_over_the_frame(convention: str) -> None:
    cam = Camera(**LENS, convention=convention)  # type: ignore[arg-type]
    uv = frame_pixels(cam)
    rays = cam.unproject(uv)
    depth = np.random.default_rng(0).uniform(2.0, 50.0, len(rays))
    back = cam.project(rays * depth[:, None])
    assert np.abs(back - uv).max() < 1e-6
    assert np.allclose(np.linalg.norm(rays, axis=1), 1.0)


def test_distort_ideal_equals_opencv_projection() -> None:
    cam = Camera(**LENS)
    rng = np.random.default_rng(1)
    points = np.column_stack([rng.uniform(-0.6, 0.6, (500, 2)), np.ones(500)]) * rng.uniform(1, 20, (500, 1))
    ours = cam.project(points)
    theirs, _ = cv2.projectPoints(points, np.zeros(3), np.zeros(3), cam.matrix(), cam.opencv_distortion())
    assert np.abs(ours - theirs.reshape(-1, 2)).max() < 1e-9
    back = cv2.undistortPoints(
        ours.reshape(-1, 1, 2),
        cam.matrix(),
        cam.opencv_distortion(),
        criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-14),
    )
    assert np.abs(cam.pixel_to_normalised(ours) - back.reshape(-1, 2)).max() < 1e-8


# A survey-drone lens: about 34 px of radial and 0.5 px of decentring distortion at the corners.
DRONE_LENS = {**LENS, "k1": -0.05, "k2": 0.01, "k3": 0.0, "t1": 1.5e-4, "t2": -1e-4}


@pytest.mark.parametrize("source", ["distort_ideal", "restore_ideal"])
@pytest.mark.parametrize(("lens", "bound_px"), [(DRONE_LENS, 0.05), (LENS, 0.5)], ids=["drone", "wide"])
def test_converting_convention_keeps_the_pixel_mapping(source: str, lens: dict, bound_px: float) -> None:
    # The inverse of a Brown polynomial is not one: radial x tangential cross terms are left over, which
    # is why the wide-angle lens (130 px of distortion, 1.7 px tangential) converts only to 0.5 px.
    cam = Camera(**lens, convention=source)
    other = cam.with_convention("restore_ideal" if source == "distort_ideal" else "distort_ideal")
    assert other.convention != cam.convention
    uv = frame_pixels(cam, 61)
    rays = cam.unproject(uv)
    assert np.abs(other.project(rays) - uv).max() < bound_px
    # and the coefficients really changed: the same numbers in the other convention are far off
    naive = cam.replace(convention=other.convention)
    assert np.abs(naive.project(rays) - uv).max() > 1.0


@pytest.mark.parametrize("convention", ["distort_ideal", "restore_ideal"])
def test_project_jacobian_matches_finite_differences(convention: str) -> None:
    cam = Camera(**LENS, convention=convention)  # type: ignore[arg-type]
    rng = np.random.default_rng(2)
    points = np.column_stack([rng.uniform(-0.5, 0.5, (50, 2)), np.ones(50)]) * rng.uniform(2, 10, (50, 1))
    jac = cam.project_jacobian(points)
    h = 1e-6
    for axis in range(3):
        step = np.zeros(3)
        step[axis] = h
        numeric = (cam.project(points + step) - cam.project(points - step)) / (2 * h)
        assert np.abs(jac[:, :, axis] - numeric).max() < 1e-4 * np.abs(numeric).max()


def test_undistort_maps_equal_opencv() -> None:
    cam = Camera(**{**LENS, "width": 400, "height": 300, "cx": 201.0, "cy": 148.0, "fx": 300.0, "fy": 300.0})
    map_x, map_y = cam.undistort_maps()
    cv_x, cv_y = cv2.initUndistortRectifyMap(
        cam.matrix(), cam.opencv_distortion(), None, cam.matrix(), (cam.width, cam.height), cv2.CV_32FC1
    )
    assert np.abs(map_x - cv_x).max() < 1e-3
    assert np.abs(map_y - cv_y).max() < 1e-3


def test_rotation_vectors_match_opencv_including_half_turns() -> None:
    rng = np.random.default_rng(3)
    vectors = [rng.normal(size=3) for _ in range(20)] + [np.array([0.0, np.pi, 0.0]), np.array([1e-9, 0, 0])]
    axis = np.array([1.0, 2.0, -0.5]) / np.linalg.norm([1.0, 2.0, -0.5])
    vectors.append(axis * (np.pi - 1e-7))
    for r in vectors:
        R = rotation_from_vector(r)
        assert np.allclose(R, cv2.Rodrigues(r)[0], atol=1e-12)
        assert np.allclose(rotation_from_vector(vector_from_rotation(R)), R, atol=1e-9)


def test_world_to_camera_uses_centre_convention() -> None:
    R = rotation_from_vector(np.array([0.1, -0.2, 0.3]))
    C = np.array([10.0, -4.0, 100.0])
    assert np.allclose(world_to_camera(C[None], R, C), 0.0)
    assert np.allclose(world_to_camera((C + R.T @ [0, 0, 5.0])[None], R, C), [[0, 0, 5.0]])


def test_json_round_trip_and_bad_input() -> None:
    cam = Camera(**LENS, convention="restore_ideal")
    assert Camera.from_json(cam.to_json()) == cam
    good = cam.to_json()
    for bad, message in [
        ({**good, "fx": -1.0}, "fx"),
        ({**good, "width": 0}, "width"),
        ({**good, "convention": "fisheye"}, "convention"),
        ({**good, "k1": "x"}, "k1"),
        ({**good, "model": "kannala"}, "model"),
        ([1, 2], "object"),
    ]:
        with pytest.raises(ValueError, match=message):
            Camera.from_json(bad)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="distort_ideal"):
        cam.opencv_distortion()
