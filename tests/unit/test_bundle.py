"""Bundle adjustment and reconstruction on synthetic scenes with known truth (tests/sfm_scenes.py):
a ring of oblique and a ring of nadir cameras over ground with relief, Brown distortion, 0.5 px RMS
noise and 10 % wrong matches."""

from __future__ import annotations

import json

import numpy as np
import pytest

from tests.sfm_scenes import ground_height, make_sfm_scene, similarity_align
from workers.algorithms.geometry import (
    rotation_from_vector,
    rotations_from_vectors,
    vector_from_rotation,
    world_to_camera,
)
from workers.algorithms.sfm import (
    Attitude,
    BundleOptions,
    BundleProblem,
    GpsFix,
    GroundControlPoint,
    ReconstructionOptions,
    adjust,
    reconstruct,
    refine_points,
    reproject,
    rms,
    robust_rho,
    rotation_from_attitude,
    triangulate_rays,
)


@pytest.fixture(scope="module")
def scene():
    return make_sfm_scene(n_ring=14, n_nadir=8, n_points=2000, seed=0)


def aligned_centre_errors(rec, scene) -> np.ndarray:
    """|C - C_true| per registered frame after the best similarity (for an arbitrary-frame model)."""
    frames = sorted(rec.poses)
    C = np.array([rec.poses[f][1] for f in frames])
    s, R, t = similarity_align(C, scene.centres[frames])
    return np.linalg.norm(s * C @ R.T + t - scene.centres[frames], axis=1)


def test_vectorised_rodrigues_and_projection_match_the_camera_model() -> None:
    rng = np.random.default_rng(0)
    rvecs = np.vstack([rng.normal(0, 1, (20, 3)), [[0, 0, 0], [1e-10, 0, 0], [np.pi - 1e-7, 0, 0]]])
    R = rotations_from_vectors(rvecs)
    assert np.abs(R - np.array([rotation_from_vector(r) for r in rvecs])).max() < 1e-12
    cam = make_sfm_scene(n_ring=2, n_nadir=0, n_points=10).camera
    centres = rng.normal(0, 5, (23, 3))
    points = rng.normal(0, 5, (50, 3)) + [0, 0, 40]
    frame, point = rng.integers(0, 23, 200), rng.integers(0, 50, 200)
    ours = reproject(cam, rvecs, centres, points, frame, point)
    pairs = list(zip(frame, point, strict=True))
    ok = np.array([world_to_camera(points[p][None], R[f], centres[f])[0, 2] > 0 for f, p in pairs])
    reference = np.array([cam.project(world_to_camera(points[p][None], R[f], centres[f]))[0] for f, p in pairs])
    assert np.allclose(ours[ok], reference[ok], rtol=1e-10, atol=1e-8)


def test_loss_derivatives_are_consistent() -> None:
    z = np.linspace(0.01, 9.0, 50)
    for kind in ("linear", "soft_l1", "huber", "cauchy", "arctan"):
        rho = robust_rho(kind, z)
        h = 1e-6
        up, down = robust_rho(kind, z + h), robust_rho(kind, z - h)
        assert np.allclose((up[0] - down[0]) / (2 * h), rho[1], atol=1e-5), kind
        assert np.allclose((up[1] - down[1]) / (2 * h), rho[2], atol=1e-4), kind
    assert np.isclose(robust_rho("soft_l1", np.array([3.0]))[0, 0], 2.0)
    with pytest.raises(ValueError):
        robust_rho("tukey", z)


def test_triangulation_and_point_refinement_hit_the_truth(scene) -> None:
    frames = np.repeat(np.arange(5), 40)
    pts = np.tile(np.arange(40), 5)
    seen = np.array(
        [
            (world_to_camera(scene.points[p][None], scene.rotations[f], scene.centres[f]))[0, 2] > 0
            for f, p in zip(frames, pts, strict=True)
        ]
    )
    frames, pts = frames[seen], pts[seen]
    xy = np.array([scene.project(f, scene.points[p][None])[0] for f, p in zip(frames, pts, strict=True)])
    rays = np.einsum("kji,kj->ki", scene.rotations[frames], scene.camera.unproject(xy))  # R^T ray
    X, ok = triangulate_rays(scene.centres[frames], rays, pts, 40)
    assert ok.all() and np.abs(X - scene.points[:40]).max() < 1e-6
    rng = np.random.default_rng(1)
    refined = refine_points(
        scene.camera, scene.rotations[frames], scene.centres[frames], xy, pts, X + rng.normal(0, 0.5, X.shape)
    )
    assert np.abs(refined - scene.points[:40]).max() < 1e-6


def test_bundle_adjustment_recovers_cameras_intrinsics_and_rejects_outliers(scene) -> None:
    """Truth tracks, 5 % observations moved by ~30 px; start: 0.5 m, 0.6 degree, focal 3 % off, no distortion."""
    frame = np.concatenate([np.full(len(f), k) for k, f in enumerate(scene.features)])
    point, xy = np.concatenate(scene.feature_point), np.concatenate(scene.features).copy()
    rng = np.random.default_rng(2)
    bad = rng.random(len(xy)) < 0.05
    xy[bad] += rng.normal(0, 30, (bad.sum(), 2))
    n = len(scene.centres)
    rvecs = np.array([vector_from_rotation(R) for R in scene.rotations]) + rng.normal(0, 0.01, (n, 3))
    problem = BundleProblem(
        scene.camera.replace(fx=1030.0, fy=1030.0, k1=0.0, k2=0.0),
        rvecs,
        scene.centres + rng.normal(0, 0.5, (n, 3)),
        scene.points + rng.normal(0, 0.3, (len(scene.points), 3)),
        frame,
        point,
        xy,
        gps_frame=np.arange(n),
        gps_xyz=scene.centres + rng.normal(0, 0.02, (n, 3)),
        gps_sigma=np.full((n, 3), 0.02),
    )
    result = adjust(problem, BundleOptions(refine_focal=True, refine_k1=True, refine_k2=True))
    assert rms(result.residuals[result.inlier]) < 0.55
    assert ((~result.inlier) & bad).sum() / bad.sum() > 0.95  # planted outliers are rejected ...
    assert ((~result.inlier) & ~bad).sum() / (~bad).sum() < 0.005  # ... and few good observations
    assert abs(result.camera.fx / 1000.0 - 1) < 0.002 and abs(result.camera.k1 + 0.08) < 0.005
    assert np.linalg.norm(result.centres - scene.centres, axis=1).max() < 0.05


@pytest.fixture(scope="module")
def free_model(scene):
    return reconstruct(scene.features, scene.matches, scene.camera)


def test_reconstruction_without_gps_is_the_truth_up_to_a_similarity(scene, free_model) -> None:
    rec = free_model
    assert rec.report["frames"]["registered"] == len(scene.centres) and not rec.report["frames"]["not_registered"]
    assert "arbitrary" in rec.report["world_frame"] and rec.report["datum"] == "none"
    errors = aligned_centre_errors(rec, scene)
    assert errors.max() < 1e-3 * scene.size, f"worst centre {errors.max():.3f} m of {scene.size:.0f} m"
    assert rec.report["rms_reprojection_px"] <= 0.6
    assert all(f["rms_px"] < 0.7 for f in rec.report["per_frame"].values())
    assert len(rec.points) > 0.5 * len(scene.points)
    json.dumps(rec.report)  # JSON-serialisable
    assert rec.residuals.residual.shape == rec.residuals.xy.shape and rec.residuals.inlier.mean() > 0.97


def test_the_first_baseline_sets_the_scale_without_gps(free_model) -> None:
    i, j = (int(v) for v in free_model.report["initialisation"].split("frames ")[1].split(" and "))
    assert abs(np.linalg.norm(free_model.poses[i][1] - free_model.poses[j][1]) - 1.0) < 1e-6


def test_self_calibration_finds_focal_and_distortion(scene) -> None:
    start = scene.camera.replace(fx=1030.0, fy=1030.0, k1=0.0, k2=0.0)
    rec = reconstruct(
        scene.features,
        scene.matches,
        start,
        options=ReconstructionOptions(refine_focal=True, refine_k1=True, refine_k2=True),
    )
    assert abs(rec.camera.fx / scene.camera.fx - 1.0) < 0.005
    assert abs(rec.camera.fy / scene.camera.fy - 1.0) < 0.005
    assert abs(rec.camera.k1 - scene.camera.k1) < 0.01
    assert rec.report["rms_reprojection_px"] <= 0.6
    assert aligned_centre_errors(rec, scene).max() < 1e-3 * scene.size


def test_gps_priors_fix_the_datum(scene) -> None:
    rng = np.random.default_rng(5)
    gps = {f: GpsFix(tuple(scene.centres[f] + rng.normal(0, 0.05, 3)), 0.05, 0.05) for f in range(len(scene.centres))}
    rec = reconstruct(scene.features, scene.matches, scene.camera, gps=gps)
    assert rec.report["datum"] == "similarity_to_gps_and_gcps" and rec.report["world_frame"].startswith("local")
    C = np.array([rec.poses[f][1] for f in range(len(scene.centres))])
    assert np.linalg.norm(C - scene.centres, axis=1).max() < 1e-3 * scene.size  # no similarity applied
    sel = np.abs(rec.points[:, :2]).max(axis=1) < 44
    heights = rec.points[sel, 2] - ground_height(rec.points[sel, 0], rec.points[sel, 1])
    assert np.percentile(np.abs(heights), 95) < 0.1  # the points lie on the true ground
    residuals = [f["gps_residual_m"] for f in rec.report["per_frame"].values()]
    assert len(residuals) == len(scene.centres) and max(residuals) < 0.2


def test_gcps_give_the_datum_and_checkpoints_measure_it(scene) -> None:
    rng = np.random.default_rng(6)
    names = [f"img_{f:02d}.jpg" for f in range(len(scene.centres))]
    xy = rng.uniform(-30, 30, (8, 2))
    truth = np.column_stack([xy, ground_height(xy[:, 0], xy[:, 1])])
    gcps = []
    for g, X in enumerate(truth):
        observed = {}
        for f in range(len(names)):
            cam = scene.rotations[f] @ (X - scene.centres[f])
            px = scene.project(f, X[None])[0]
            if cam[2] > 0 and np.all((px > 0) & (px < [1199, 899])) and len(observed) < 5:
                observed[names[f]] = px + rng.normal(0, 0.3, 2)
        gcps.append(GroundControlPoint(f"g{g}", truth[g] + rng.normal(0, 0.01, 3), observed))
    gcps.append(GroundControlPoint("tie", None, dict(list(gcps[0].observations.items())[:3])))
    rec = reconstruct(
        scene.features, scene.matches, scene.camera, gcps=gcps, checkpoints={"g0", "g1", "g2"}, frame_names=names
    )
    report = rec.report["gcps"]
    assert rec.report["datum"] == "similarity_to_gps_and_gcps"
    assert [report[f"g{k}"]["role"] for k in range(4)] == ["checkpoint"] * 3 + ["control"]
    assert report["tie"]["role"] == "tie" and report["tie"]["rms_px"] < 1.0
    assert rec.report["checkpoint_rmse_m"] < 0.08
    assert all(report[f"g{k}"]["rms_px"] < 1.0 and report[f"g{k}"]["residual_m"] < 0.05 for k in range(3, 8))
    C = np.array([rec.poses[f][1] for f in range(len(scene.centres))])
    assert np.linalg.norm(C - scene.centres, axis=1).max() < 1e-3 * scene.size
    assert np.linalg.norm(rec.gcp_positions["tie"] - truth[0]) < 0.1  # the tie point sits on g0


def test_dji_attitude_convention(scene) -> None:
    for f in range(len(scene.centres)):  # the scene computes yaw / pitch / roll from its look-at geometry
        assert np.abs(rotation_from_attitude(Attitude(*scene.attitude[f])) - scene.rotations[f]).max() < 1e-9
    nadir = rotation_from_attitude(Attitude(yaw=0.0, pitch=-90.0, roll=0.0))
    assert np.allclose(nadir[2], [0, 0, -1]) and np.allclose(-nadir[1], [0, 1, 0])  # looks down, image top north
    east = rotation_from_attitude(Attitude(yaw=90.0, pitch=0.0, roll=10.0))
    assert np.allclose(east[2], [1, 0, 0]) and east[0][2] < 0  # looks east; positive roll: right side down


def test_cameras_from_gps_and_attitude(scene) -> None:
    rng = np.random.default_rng(8)
    n = len(scene.centres)
    gps = {f: GpsFix(tuple(scene.centres[f] + rng.normal(0, 0.1, 3)), 0.1, 0.1) for f in range(n)}
    attitude = {f: Attitude(*(scene.attitude[f] + rng.normal(0, 2.0, 3))) for f in range(n)}
    rec = reconstruct(scene.features, scene.matches, scene.camera, gps=gps, attitude=attitude)
    assert rec.report["initialisation"] == "gps_attitude" and rec.report["frames"]["registered"] == n
    C = np.array([rec.poses[f][1] for f in range(n)])
    assert np.linalg.norm(C - scene.centres, axis=1).max() < 1e-3 * scene.size
    angle = [np.degrees(np.linalg.norm(vector_from_rotation(rec.poses[f][0] @ scene.rotations[f].T))) for f in range(n)]
    assert max(angle) < 0.2  # GPS noise 0.1 m at 50-90 m range
    assert rec.report["rms_reprojection_px"] <= 0.6


def test_too_little_data_is_an_empty_result_and_misuse_raises(scene) -> None:
    rec = reconstruct(scene.features[:3], {}, scene.camera)
    assert rec.poses == {} and len(rec.points) == 0 and rec.report["frames"]["registered"] == 0
    assert set(rec.report["frames"]["not_registered"]) == {"0", "1", "2"}
    with pytest.raises(ValueError):
        reconstruct(scene.features[:2], {(0, 5): (np.zeros(1, int), np.zeros(1, int))}, scene.camera)
    with pytest.raises(ValueError):
        reconstruct(scene.features[:2], {}, scene.camera, gps={7: GpsFix((0.0, 0.0, 0.0))})
    with pytest.raises(ValueError):
        adjust(
            BundleProblem(
                scene.camera,
                np.zeros((1, 3)),
                np.zeros((2, 3)),
                np.zeros((0, 3)),
                np.zeros(0, int),
                np.zeros(0, int),
                np.zeros((0, 2)),
            )
        )
