"""Calibration on seeded synthetic scenes with planted truth, and against OpenCV on real chessboards."""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from tests.calib_scenes import (
    LENS,
    LENS_RESTORE,
    board_scene,
    mapping_error_px,
    render_chessboard,
    stereo_scene,
    straight_lines,
)
from tests.conftest import shared_data
from workers.algorithms.calibration import (
    CalibrationResult,
    board_points,
    calibrate_camera,
    find_chessboard,
    paired_points,
    plumb_line,
    stereo_calibrate,
)
from workers.algorithms.geometry import Camera, vector_from_rotation

CAMERAS = {"distort_ideal": LENS, "restore_ideal": LENS_RESTORE}
NOISE_RMS = 0.2 * math.sqrt(2)  # RMS point error of 0.2 px Gaussian noise per coordinate
PAIRS = ("01", "02", "03", "04", "05", "06", "07", "08", "09", "11", "12", "13", "14")  # *10 is missing upstream


def frame_grid(cam: Camera, n: int = 25) -> np.ndarray:
    u, v = np.meshgrid(np.linspace(0, cam.width - 1, n), np.linspace(0, cam.height - 1, n))
    return np.stack([u.ravel(), v.ravel()], axis=1)


def mapping_sigma_px(result: CalibrationResult, rays: np.ndarray) -> np.ndarray:
    """(N,) predicted standard error of the estimated camera's pixel for each ray, from the covariance."""
    cam, names = result.camera, result.parameter_names
    jac = np.empty((len(rays), 2, len(names)))
    for k, name in enumerate(names):
        h = 1e-6 * max(1.0, abs(getattr(cam, name)))
        plus = cam.replace(**{name: getattr(cam, name) + h}).normalised_to_pixel(rays)
        minus = cam.replace(**{name: getattr(cam, name) - h}).normalised_to_pixel(rays)
        jac[:, :, k] = (plus - minus) / (2 * h)
    return np.sqrt(np.einsum("nik,kl,nil->n", jac, result.covariance, jac))


def test_board_points_follow_opencv_corner_order() -> None:
    pts = board_points((9, 6), 25.0)
    assert pts.shape == (54, 3) and not pts[:, 2].any()
    assert np.allclose(pts[1], [25, 0, 0]) and np.allclose(pts[9], [0, 25, 0]) and np.allclose(pts[-1], [200, 125, 0])
    with pytest.raises(ValueError, match="square must be a positive length"):
        board_points((9, 6), 0.0)
    with pytest.raises(ValueError, match="pattern must be"):
        board_points((9, 1), 1.0)


def test_find_chessboard_locates_rendered_corners_to_a_few_hundredths_of_a_pixel() -> None:
    H = np.array([[0.6, -0.3, 250.0], [0.25, 0.55, 60.0], [-2e-4, 3e-4, 1.0]])  # tilted, rotated, shrunk
    image, truth = render_chessboard((9, 6), 40, H, (640, 480))
    found = find_chessboard(image, (9, 6))
    assert found is not None and found.shape == (54, 2) and found.dtype == np.float64
    error = min(np.abs(found - truth).max(), np.abs(found[::-1] - truth).max())  # a half turn is OpenCV's too
    assert error < 0.1
    assert find_chessboard(np.full((480, 640), 128, np.uint8), (9, 6)) is None
    with pytest.raises(ValueError, match="uint8 grey image"):
        find_chessboard(image.astype(np.float32), (9, 6))


@pytest.mark.parametrize("convention", ["distort_ideal", "restore_ideal"])
def test_calibration_recovers_a_planted_lens_exactly_without_noise(convention: str) -> None:
    truth = CAMERAS[convention]
    scene = board_scene(truth, n_views=8, noise_px=0.0, seed=5)
    result = calibrate_camera(scene.views, truth.width, truth.height, convention)  # type: ignore[arg-type]
    assert result.camera.convention == convention
    assert result.rms_px < 1e-6
    assert mapping_error_px(result.camera, truth) < 1e-4
    assert np.abs(result.centres - scene.centres).max() < 1e-5  # mm
    assert np.abs(result.rotations - scene.rotations).max() < 1e-8


@pytest.mark.parametrize("convention", ["distort_ideal", "restore_ideal"])
def test_calibration_under_noise_is_as_close_as_its_reported_uncertainty(convention: str) -> None:
    truth = CAMERAS[convention]
    scene = board_scene(truth, n_views=15, noise_px=0.2, seed=0)
    result = calibrate_camera(scene.views, truth.width, truth.height, convention)  # type: ignore[arg-type]
    assert abs(result.rms_px - NOISE_RMS) < 0.02
    for name in ("fx", "fy", "cx", "cy"):
        assert abs(getattr(result.camera, name) - getattr(truth, name)) < 4 * result.std[name], name
        assert result.std[name] < 0.4, name  # px: 15 views of ~170 points pin the camera matrix down
    uv = frame_grid(truth)
    rays = truth.pixel_to_normalised(uv)
    error = np.linalg.norm(result.camera.normalised_to_pixel(rays) - uv, axis=1)
    assert error.max() < 0.5  # px, over the whole frame, corners included (~140 px of distortion there)
    assert (error / mapping_sigma_px(result, rays)).max() < 4.0  # and within what the covariance predicts


def test_planted_bad_marks_have_the_largest_point_errors() -> None:
    scene = board_scene(LENS, n_views=10, noise_px=0.2, seed=3)
    views = [(obj, px.copy()) for obj, px in scene.views]
    views[4][1][[3, 17, 40]] += [[4.0, -3.0], [-5.0, 0.0], [0.0, 4.0]]  # three mis-clicked corners in view 4
    result = calibrate_camera(views, LENS.width, LENS.height)
    worst = result.worst_points(3)
    assert sorted((v, i) for v, i, _ in worst) == [(4, 3), (4, 17), (4, 40)]
    assert min(e for *_, e in worst) > 3.0 > 1.5 > sorted(np.concatenate(result.errors))[-4]
    assert int(np.argmax(result.view_rms_px)) == 4
    assert [len(e) for e in result.errors] == [len(obj) for obj, _ in views]
    assert np.allclose(np.linalg.norm(result.residuals[4], axis=1), result.errors[4])


def test_calibration_rejects_misuse_with_clear_messages() -> None:
    views = board_scene(LENS, n_views=4, seed=1).views
    with pytest.raises(ValueError, match="at least 3 views of the target, got 2"):
        calibrate_camera(views[:2], 1280, 960)
    with pytest.raises(ValueError, match="view 0 has 5 points; each view needs at least 6"):
        calibrate_camera([(obj[:5], px[:5]) for obj, px in views], 1280, 960)
    with pytest.raises(ValueError, match=r"view 1: image points must be \(N, 2\)"):
        calibrate_camera([views[0], (views[1][0], views[1][1][:-1]), views[2]], 1280, 960)
    with pytest.raises(ValueError, match="terms must be distinct names"):
        calibrate_camera(views, 1280, 960, terms=("k1", "k4"))
    with pytest.raises(ValueError, match="unknown convention"):
        calibrate_camera(views, 1280, 960, convention="fisheye")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="non-planar target"):
        calibrate_camera([(obj + [0, 0, 1e-3 * i], px) for i, (obj, px) in enumerate(views)], 1280, 960)


@pytest.mark.parametrize("convention", ["distort_ideal", "restore_ideal"])
def test_plumb_line_recovers_planted_radial_and_tangential_terms(convention: str) -> None:
    truth = LENS.replace(k3=0.0).with_convention(convention).replace(k3=0.0)  # type: ignore[arg-type]
    start = truth.replace(k1=0.0, k2=0.0, t1=0.0, t2=0.0)
    exact = plumb_line(straight_lines(truth, noise_px=0.0), start)
    assert exact.rms_px < 1e-9 and mapping_error_px(exact.camera, truth) < 1e-6
    lines = straight_lines(truth, n_lines=40, n_points=80, noise_px=0.03, seed=4)
    result = plumb_line(lines, start)
    assert result.camera.convention == convention and result.camera.fx == truth.fx
    assert mapping_error_px(result.camera, truth) < 0.1
    assert 0.025 < result.rms_px < 0.035 and result.line_rms_px.shape == (40,)
    for name in ("k1", "k2"):
        assert abs(getattr(result.camera, name) - getattr(truth, name)) < 4 * result.std[name], name


def test_plumb_line_rejects_misuse() -> None:
    cam = LENS.replace(k1=0.0, k2=0.0, k3=0.0, t1=0.0, t2=0.0)
    line = np.stack([np.linspace(0, 600, 10), np.linspace(0, 300, 10)], axis=1)
    with pytest.raises(ValueError, match="at least 2 lines, got 1"):
        plumb_line([line], cam)
    with pytest.raises(ValueError, match="line 1 must be finite"):
        plumb_line([line, line[:2]], cam)
    with pytest.raises(ValueError, match="terms must be distinct"):
        plumb_line([line, line + 50], cam, terms=("k1", "k1"))


def test_stereo_calibration_recovers_the_planted_rig() -> None:
    scene = stereo_scene(seed=1)
    result = stereo_calibrate(scene.left, scene.right, scene.views)
    truth_baseline = float(np.linalg.norm(scene.T))
    assert abs(result.rms_px - NOISE_RMS) < 0.03
    assert abs(result.baseline - truth_baseline) < max(4 * result.baseline_std, 1e-3) and result.baseline_std < 0.2
    assert math.degrees(np.linalg.norm(vector_from_rotation(result.R @ scene.R.T))) < 0.03
    assert np.allclose(result.rig.to_json()["T"], result.T) and result.reversed_views == ()
    assert [len(e) for e in result.errors_right] == [len(v[0]) for v in scene.views]


def test_stereo_covariance_matches_the_scatter_of_repeated_calibrations() -> None:
    pulls = []
    for seed in range(8):
        scene = stereo_scene(n_views=6, seed=20 + seed)
        result = stereo_calibrate(scene.left, scene.right, scene.views)
        error = np.concatenate([vector_from_rotation(result.R) - vector_from_rotation(scene.R), result.T - scene.T])
        pulls.append(error / np.sqrt(np.diag(result.covariance)))
    assert 0.6 < float(np.sqrt(np.mean(np.square(pulls)))) < 1.5  # 1 when the covariance is honest


def test_stereo_calibration_undoes_a_board_found_in_reverse_order() -> None:
    scene = stereo_scene(seed=1)
    straight = stereo_calibrate(scene.left, scene.right, scene.views)
    views = [(obj, lpx, rpx[::-1]) if v in (2, 5) else (obj, lpx, rpx) for v, (obj, lpx, rpx) in enumerate(scene.views)]
    result = stereo_calibrate(scene.left, scene.right, views)
    assert result.reversed_views == (2, 5)
    assert abs(result.baseline - straight.baseline) < 1e-6
    assert np.allclose(result.errors_right[2], straight.errors_right[2][::-1])  # in the order the caller gave


def test_a_pair_keeps_the_marks_both_photos_have_and_a_reversed_board_can_still_be_turned() -> None:
    scene = stereo_scene(seed=1)
    straight = stereo_calibrate(scene.left, scene.right, scene.views)
    obj, lpx, rpx = scene.views[0]
    assert all(a is b for a, b in zip(paired_points((obj, lpx), (obj, rpx)), (obj, lpx, rpx), strict=True))
    # right points marked by hand with their own board points, in reverse order: matched by board point
    both = paired_points((obj, lpx), (obj[::-1], rpx[::-1]))
    assert np.array_equal(both[0], obj) and np.array_equal(both[2], rpx)
    # marks 7 and 40 removed from each left photo; the corners of views 2 and 5 found in reverse in the right one
    centre, gone = obj.mean(axis=0), [7, 40]
    views, loose = [], []
    for v, (o, lp, rp) in enumerate(scene.views):
        right = (o, rp[::-1]) if v in (2, 5) else (o, rp)
        views.append(paired_points((np.delete(o, gone, 0), np.delete(lp, gone, 0)), right, centre))
        loose.append(paired_points((np.delete(o, gone, 0), np.delete(lp, gone, 0)), right))
    assert [len(v[0]) for v in views] == [len(obj) - 4] * len(views)  # and the marks opposite 7 and 40
    assert not any(np.allclose(p, obj[k]) or np.allclose(p, obj[-1 - k]) for p in views[0][0] for k in gone)
    result = stereo_calibrate(scene.left, scene.right, views)
    assert result.reversed_views == (2, 5) and abs(result.baseline - straight.baseline) < 0.05
    assert result.rms_px < 1.1 * straight.rms_px
    # without the half-turn closure the reversed views cannot be turned round: they spoil the solve
    assert stereo_calibrate(scene.left, scene.right, loose).rms_px > 10 * straight.rms_px


def test_stereo_calibration_rejects_misuse() -> None:
    scene = stereo_scene(n_views=3, seed=2)
    with pytest.raises(ValueError, match="at least 3 views"):
        stereo_calibrate(scene.left, scene.right, scene.views[:2])
    with pytest.raises(ValueError, match=r"view 0: expected 3 arrays"):
        stereo_calibrate(scene.left, scene.right, [v[:2] for v in scene.views])  # type: ignore[misc]
    bad = [(obj, lpx, rpx[:-1]) for obj, lpx, rpx in scene.views]
    with pytest.raises(ValueError, match=r"view 0: image points must be \(N, 2\)"):
        stereo_calibrate(scene.left, scene.right, bad)


# -- real chessboards (OpenCV's stereo sample set) -------------------------------------------------------
@pytest.fixture(scope="module")
def chessboards() -> dict[str, list[np.ndarray]]:
    folder = shared_data("calib_chessboard")
    corners: dict[str, list[np.ndarray]] = {}
    for side in ("left", "right"):
        found = [find_chessboard(read_gray(folder / f"{side}{n}.jpg"), (9, 6)) for n in PAIRS]
        assert all(c is not None for c in found), f"no board in some {side} images"
        corners[side] = [c for c in found if c is not None]
    return corners


def read_gray(path: Path) -> np.ndarray:
    gray = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    assert gray is not None, f"cannot read {path}"
    return gray


def opencv_calibration(corners: list[np.ndarray]) -> tuple[float, np.ndarray, np.ndarray]:
    obj = board_points((9, 6), 1.0).astype(np.float32)
    rms, K, dist, _, _ = cv2.calibrateCamera(
        [obj] * len(corners), [c.astype(np.float32) for c in corners], (640, 480), None, None
    )
    return rms, K, dist


@pytest.mark.realdata
@pytest.mark.parametrize("side", ["left", "right"])
def test_real_chessboards_calibrate_like_opencv(chessboards: dict[str, list[np.ndarray]], side: str) -> None:
    obj = board_points((9, 6), 1.0)
    ours = calibrate_camera([(obj, c) for c in chessboards[side]], 640, 480)
    rms, K, dist = opencv_calibration(chessboards[side])
    assert abs(ours.rms_px - rms) < 0.1 * rms
    assert np.allclose(
        [ours.camera.fx, ours.camera.fy, ours.camera.cx, ours.camera.cy],
        [K[0, 0], K[1, 1], K[0, 2], K[1, 2]],
        atol=0.05,
    )
    assert ours.rms_px < 0.3  # OpenCV's sample recipe (11 px sub-pixel window) gets 0.41 px on the left set
    restore = calibrate_camera([(obj, c) for c in chessboards[side]], 640, 480, "restore_ideal")
    assert abs(restore.rms_px - ours.rms_px) < 0.05 * ours.rms_px
    # both conventions describe the same lens where the board was seen (beyond, they extrapolate differently)
    seen = np.concatenate(chessboards[side])
    moved = restore.camera.normalised_to_pixel(ours.camera.pixel_to_normalised(seen)) - seen
    assert np.linalg.norm(moved, axis=1).max() < 0.2


@pytest.mark.realdata
def test_real_stereo_rig_agrees_with_opencv_stereo_calibrate(chessboards: dict[str, list[np.ndarray]]) -> None:
    obj = board_points((9, 6), 1.0)
    cams = {side: calibrate_camera([(obj, c) for c in chessboards[side]], 640, 480).camera for side in chessboards}
    ours = stereo_calibrate(
        cams["left"],
        cams["right"],
        list(zip([obj] * len(PAIRS), chessboards["left"], chessboards["right"], strict=True)),
    )
    f32 = [[c.astype(np.float32) for c in chessboards[side]] for side in ("left", "right")]
    rms, *_, R, T, _, _ = cv2.stereoCalibrate(
        [obj.astype(np.float32)] * len(PAIRS),
        f32[0],
        f32[1],
        cams["left"].matrix(),
        cams["left"].opencv_distortion(),
        cams["right"].matrix(),
        cams["right"].opencv_distortion(),
        (640, 480),
        flags=cv2.CALIB_FIX_INTRINSIC,
    )
    assert abs(ours.baseline - np.linalg.norm(T)) < 0.01 * np.linalg.norm(T)
    assert math.degrees(np.linalg.norm(vector_from_rotation(ours.R @ R.T))) < 0.05
    assert abs(ours.rms_px - rms) < 0.1 * rms and ours.reversed_views == ()
    assert 3.0 < ours.baseline < 3.6 and ours.baseline_std < 0.01  # squares; ~3.3 in OpenCV's sample
