"""Stereo DEM jobs' stages run over a workspace on pairs with known truth: an RPC pair rendered from a known
terrain (the DSM goal: median error <= 0.5 GSD, completeness >= 95 %), a rectified pair, the same pair
warped and rectified from its matched features, a calibrated rig's pair of a plane, and the Middlebury pairs
scored densely as the disparity benchmark scores them."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
import rasterio
from rio_cogeo.cogeo import cog_validate

from tests.conftest import shared_data
from tests.stereo_scenes import RpcPair, dsm_accuracy, make_rectified_pair, make_rig_pair, make_rpc_pair
from workers.algorithms.calibration import StereoRig
from workers.algorithms.disparity import read_pair, score_disparity
from workers.algorithms.geometry import Camera, rotation_from_vector
from workers.algorithms.stereo import Rectification, rig_rectification
from workers.config import build_config
from workers.pipeline import PipelineError, run_stage, stage_names
from workers.workspace import JobWorkspace


def run_job(root: Path, left: Path, right: Path, options: dict[str, Any]) -> JobWorkspace:
    """The stereo DEM pipeline over ``left`` and ``right`` as the API would queue it (geometry decided)."""
    ws = JobWorkspace(root)
    ws.save_config(build_config("stereo_dem", options).model_dump())
    frames = []
    for side, path in (("left", left), ("right", right)):
        image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        frames.append({"name": path.name, "side": side, "pair": 0, "width": image.shape[1], "height": image.shape[0]})
        frames[-1]["path"] = str(path)
    ws.save_inputs(frames)
    for name in stage_names("stereo_dem"):
        run_stage(ws, "stereo_dem", name)
    return ws


@pytest.fixture(scope="module")
def rpc_pair(tmp_path_factory: pytest.TempPathFactory) -> RpcPair:
    return make_rpc_pair(tmp_path_factory.mktemp("rpc_pair"))


@pytest.mark.parametrize("method", ["sgbm", "local"])
def test_rpc_pair_dsm_meets_the_goal(tmp_path: Path, rpc_pair: RpcPair, method: str) -> None:
    assert rpc_pair.rpc_fit_px < 1e-3
    ws = run_job(tmp_path / "job", rpc_pair.left, rpc_pair.right, {"geometry": "rpc", "method": method})
    report = ws.load_report()
    assert report["geometry"] == "rpc" and report["rectification"]["row_residual_px"] < 0.1
    assert report["surface"]["epsg"] == rpc_pair.epsg and abs(report["surface"]["resolution_m"] - 1.0) < 0.05
    accuracy = dsm_accuracy(rpc_pair, ws.dsm_path(), ws.dsm_mask_path())
    assert accuracy.cells > 50_000
    # the goal: 0.5 GSD and 95 %; measured: sgbm 0.16 m and 96 %, local 0.09 m and 99.9 %
    assert accuracy.median_error_m <= 0.5 * rpc_pair.gsd_m, accuracy
    assert accuracy.completeness >= 0.95, accuracy
    with rasterio.open(ws.dsm_path()) as src:
        assert src.dtypes[0] == "float32" and src.nodata == -9999.0 and src.crs.is_projected
        assert src.crs.to_epsg() == rpc_pair.epsg
    assert cog_validate(str(ws.dsm_path()))[0]
    assert set(report["outputs"]) >= {"dsm.tif", "dsm_mask.tif", "disparity.tif", "confidence.tif"}


def test_rpc_dsm_flags_what_it_fills(tmp_path: Path, rpc_pair: RpcPair) -> None:
    """Without filling, cells no checked disparity reached have no height; with it they are flagged 2."""
    bare = run_job(tmp_path / "bare", rpc_pair.left, rpc_pair.right, {"geometry": "rpc", "fill": False})
    full = run_job(tmp_path / "full", rpc_pair.left, rpc_pair.right, {"geometry": "rpc"})
    with rasterio.open(bare.dsm_mask_path()) as a, rasterio.open(full.dsm_mask_path()) as b:
        bare_state, full_state = a.read(1), b.read(1)
    with rasterio.open(bare.disparity_path()) as src:
        disparity = src.read(1)
    with rasterio.open(bare.confidence_path()) as src:
        confidence = src.read(1)
    assert not (bare_state == 2).any() and (full_state == 2).sum() > 100
    assert ((full_state == 1) | (full_state == 2)).sum() > (bare_state == 1).sum()
    assert np.isnan(disparity).any() and (confidence[np.isnan(disparity)] == 0).all()


def _png(path: Path, image: np.ndarray) -> Path:
    cv2.imwrite(str(path), image)
    return path


def test_rectified_pair_through_the_job(tmp_path: Path) -> None:
    left, right, truth = make_rectified_pair(seed=3)
    ws = run_job(tmp_path / "job", _png(tmp_path / "l.png", left), _png(tmp_path / "r.png", right), {"rectified": True})
    with rasterio.open(ws.disparity_path()) as src:
        disparity = src.read(1)
        assert src.dtypes[0] == "float32" and src.crs is None
    inner = np.zeros(truth.shape, bool)
    inner[8:-8, 8:-8] = True
    score = score_disparity(disparity, truth, inner)
    assert score.density == 1.0 and score.bad < 0.04, score  # the occlusion beside the box's left edge
    report = ws.load_report()
    assert report["disparity"]["range_source"] == "matches" and report["surface"]["surface"] is None
    low, count = report["disparity"]["min_disparity"], report["disparity"]["num_disparities"]
    assert low <= 6 and low + count >= 15  # the truth's 6.5-14.25 px, found from SIFT matches


def test_uncalibrated_pair_is_rectified_from_its_features(tmp_path: Path) -> None:
    """The rectified pair's right photo turned by 3 degrees, shifted and sheared: rectified again from matched
    features, every matched pixel's pair of original pixels must be the true one."""
    left, right, truth = make_rectified_pair(seed=4, size=(320, 240))
    warp = np.array([[np.cos(0.05), -np.sin(0.05), 6.0], [np.sin(0.05), np.cos(0.05), -4.0], [2e-5, 1e-5, 1.0]])
    moved = cv2.warpPerspective(right, warp, (320, 240), flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)
    ws = run_job(
        tmp_path / "job", _png(tmp_path / "l.png", left), _png(tmp_path / "r.png", moved), {"geometry": "uncalibrated"}
    )
    info = ws.load_rectification()
    rect = Rectification.from_json(info["rectification"])
    assert info["inliers"] > 100 and rect.residual_px < 0.5
    dense = ws.load_disparity_arrays()["dense"]
    rows, cols = np.nonzero(np.isfinite(dense))
    xl, yl = rect.to_original("left", cols.astype(float), rows.astype(float))
    xr, yr = rect.to_original("right", cols - dense[rows, cols].astype(float), rows.astype(float))
    inside = (xl > 10) & (xl < 300) & (yl > 10) & (yl < 220)
    rows_l = np.clip(np.rint(yl), 0, truth.shape[0] - 1).astype(int)
    cols_l = np.clip(np.rint(xl), 0, truth.shape[1] - 1).astype(int)
    d_true = truth[rows_l, cols_l]
    true_right = np.column_stack([xl - d_true, yl, np.ones_like(xl)]) @ warp.T
    error = np.hypot(xr - true_right[:, 0] / true_right[:, 2], yr - true_right[:, 1] / true_right[:, 2])
    assert inside.sum() > 40_000
    assert np.mean(error[inside] < 1.0) > 0.9, np.percentile(error[inside], [50, 90])


@pytest.mark.realdata
@pytest.mark.parametrize(("name", "bound"), [("tsukuba", 0.06), ("teddy", 0.16)])
def test_middlebury_pairs_through_the_job(tmp_path: Path, name: str, bound: float) -> None:
    """The job on a real rectified pair scores as the matcher does in the disparity tests (64 disparities)."""
    folder = shared_data("stereo_middlebury") / name
    pair = read_pair(folder)
    left, right = (folder / n for n in _NAMES[name])
    ws = run_job(tmp_path / "job", left, right, {"rectified": True, "num_disparities": 64, "min_disparity": 0})
    with rasterio.open(ws.disparity_path()) as src:
        score = score_disparity(src.read(1), pair.truth, pair.mask)
    assert score.density == 1.0 and score.bad < bound, score


_NAMES = {"tsukuba": ("tsukuba_l.png", "tsukuba_r.png"), "teddy": ("im2.png", "im6.png")}


def test_a_pair_without_rpcs_cannot_be_an_rpc_pair(tmp_path: Path) -> None:
    left, right, _ = make_rectified_pair(seed=5)
    with pytest.raises(PipelineError, match="has no RPC metadata"):
        run_job(tmp_path / "job", _png(tmp_path / "l.png", left), _png(tmp_path / "r.png", right), {"geometry": "rpc"})
    assert not (tmp_path / "job" / "report.json").exists()
    assert json.loads((tmp_path / "job" / "config.json").read_text())["geometry"] == "rpc"


def test_rig_pair_gives_the_depth_of_its_plane(tmp_path: Path) -> None:
    """A rig with two distorted lenses, toed in by 3 degrees, 150 mm apart, photographs a tilted plane 1.5 m
    away: ``depth.tif`` is the plane's depth along the rectified left camera's axis."""
    left_cam = Camera(640, 480, fx=500.0, fy=501.0, cx=320.5, cy=239.2, k1=-0.22, k2=0.06, t1=4e-4)
    right_cam = Camera(
        640, 480, fx=492.5, fy=492.0, cx=316.5, cy=243.5, k1=0.2, k2=0.02, t2=-3e-4, convention="restore_ideal"
    )
    rig = StereoRig(
        left_cam, right_cam, rotation_from_vector(np.radians([0.5, -3.0, 0.2])), np.array([-150.0, 1.5, 3.0])
    )
    z0, slope = 1500.0, 0.3
    left, right = make_rig_pair(tmp_path / "photos", rig, (z0, slope, 0.0))
    ws = run_job(tmp_path / "job", left, right, {"geometry": "rig", "rig": rig.to_json()})
    with rasterio.open(ws.depth_path()) as src:
        depth = src.read(1)
    _, maps = rig_rectification(rig)  # the rotation of the rectified left camera, as the job used it
    rect = Rectification.from_json(ws.load_rectification()["rectification"])
    r1 = cv2.stereoRectify(
        left_cam.matrix(),
        left_cam.opencv_distortion(),
        right_cam.with_convention("distort_ideal").matrix(),
        right_cam.with_convention("distort_ideal").opencv_distortion(),
        (640, 480),
        rig.R,
        rig.T.reshape(3, 1),
        flags=cv2.CALIB_ZERO_DISPARITY,
        alpha=1.0,
    )[0]
    v, u = np.mgrid[0:480, 0:640].astype(np.float64)
    rays = np.column_stack([u.ravel(), v.ravel(), np.ones(u.size)]) @ np.linalg.inv(rect.left @ left_cam.matrix()).T
    rays = rays @ left_cam.matrix().T @ np.linalg.inv(left_cam.matrix()).T  # in the original left frame, undistorted
    s = z0 / (rays[:, 2] - slope * rays[:, 0])
    truth = ((s[:, None] * rays) @ r1.T)[:, 2].reshape(480, 640)
    checked = ws.load_disparity_arrays()["confidence"] > 0  # matched and checked, not filled
    valid = checked & (maps[0] > 20) & (maps[0] < 620) & (maps[1] > 20) & (maps[1] < 460)
    signed = (depth[valid] - truth[valid]) / truth[valid]
    error = np.abs(signed)
    assert valid.sum() > 150_000
    # measured: no bias (median -0.05 %), median error 0.26 % (0.13 px of its 50 px disparity), 99 % within 1 %
    assert abs(np.median(signed)) < 0.001 and np.median(error) < 0.004, np.percentile(error, [50, 95])
    assert np.mean(error < 0.01) > 0.95, np.percentile(error, [50, 95])
    assert ws.load_report()["surface"]["surface"] == "depth"
