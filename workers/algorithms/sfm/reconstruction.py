"""Photo-triangulation: camera poses and sparse points from feature matches, in the GPS / GCP frame.

``reconstruct`` is the one entry point. It (1) re-verifies every pair with a five-point essential
matrix (OpenCV USAC, Nister 2004) and builds tracks; (2) starts either from GPS + DJI attitude
(cameras directly from the metadata) or incrementally, as COLMAP (Schoenberger & Frahm 2016) and
OpenSfM do: the best initial pair by inliers and triangulation angle, then frames added one by one by
PnP (``cv2.solvePnPRansac``, SQPnP) on their 2D-3D track correspondences (or, failing that, by their
relative pose to a registered frame), new tracks triangulated and a bundle adjustment each time the
model has grown by a quarter; (3) moves an incremental model into the world frame by a similarity to
the GPS positions and control points; (4) runs the final bundle adjustment with GPS priors and GCPs
(and self-calibration when asked), rejecting outlier observations, re-admitting those that fit
afterwards and adjusting again while many do (at most three times); (5) reports.

Bundle adjustments use a spread subset of the points (``ba_points_per_frame``); every other point is
refined with the cameras held (``bundle.refine_points``), which keeps SciPy's solver affordable.

World frame: with GPS (or control points), the job's local frame ``(E - E0, N - N0, height)`` metres
(``gcp.LocalFrame``); otherwise arbitrary, scaled so that the initial pair's baseline is 1. ``GpsFix``,
``Attitude`` and ``rotation_from_attitude`` live in ``gcp`` (control measurements), imported here.
"""

from __future__ import annotations

import time
from collections.abc import Collection, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Literal

import cv2
import numpy as np

from workers.algorithms.geometry import Camera, vector_from_rotation
from workers.algorithms.sfm import bundle
from workers.algorithms.sfm.adjustment import Priors, adjust_state, gcps_triangulated, refine_all_points, to_world
from workers.algorithms.sfm.datum import (
    DATUM_GPS_ATTITUDE,
    IMAGE_STATUSES,
    Attitude,
    GpsFix,
    checkpoint_rmse,
    observations_by_frame,
    report_gcps,
)
from workers.algorithms.sfm.gcp import GroundControlPoint
from workers.algorithms.sfm.incremental import (
    ReconstructionState,
    frame_observations,
    register_by_pnp,
    register_by_relative_pose,
    reprojection_errors,
    state_rotations,
    triangulate_tracks,
    unregister,
)
from workers.algorithms.sfm.priors import check_attitude_priors
from workers.algorithms.sfm.tracks import PairMatches, Tracks, build_tracks, initial_pair, relative_pose, verify_pairs

MIN_KEPT_SHARE = 0.1  # a frame keeping fewer of the tie points its pairs offered is placed again
GPS_MISFIT_SIGMAS = 5.0  # ... or one this many GPS accuracies from its fix
GPS_WARNING_SIGMAS = 3.0  # the report warns of cameras this many GPS accuracies from their fixes


@dataclass(frozen=True)
class ReconstructionOptions:
    """Tuning of ``reconstruct``; pixels are those of the feature coordinates."""

    loss: bundle.LossName = "soft_l1"  # robust loss of the bundle adjustment (see bundle.BundleOptions)
    loss_scale_px: float = 1.0  # its f_scale, px
    outlier_threshold_px: float = 4.0  # observations reprojecting further are dropped
    refine_focal: bool = False  # self-calibrate the shared focal length
    refine_k1: bool = False  # ... and radial k1
    refine_k2: bool = False  # ... and radial k2
    focal_sigma: float = 0.05  # 1-sigma of the initial focal length, relative (a prior when refining it)
    min_track_length: int = 2  # frames a track must be seen in
    initial: Literal["auto", "incremental", "attitude"] = "auto"  # auto: attitude when every frame has GPS + attitude
    verify_threshold_px: float = 2.0  # epipolar threshold of the pair re-verification (essential matrix)
    min_pair_inliers: int = 20  # pairs with fewer verified matches are dropped
    pnp_threshold_px: float = 4.0  # PnP RANSAC reprojection threshold
    min_pnp_inliers: int = 12  # a frame needs this many PnP inliers to be registered
    min_angle_deg: float = 1.0  # a new point needs rays at least this far apart
    init_angle_deg: float = 5.0  # initial pairs with a smaller median angle are scored down
    ba_points_per_frame: int = 150  # points per frame in the adjustment; the others are refined with cameras held
    gcp_sigma_m: float = 0.05  # accuracy of control point positions
    max_nfev: int = 60  # per least-squares solve


@dataclass(frozen=True)
class ObservationResiduals:
    """Every observation of an output point: ``frame`` (K,), ``point`` (K,) row of
    ``Reconstruction.points``, ``xy`` (K, 2) observed px, ``residual`` (K, 2) projected - observed px,
    ``inlier`` (K,) bool kept by the outlier rejection."""

    frame: np.ndarray
    point: np.ndarray
    xy: np.ndarray
    residual: np.ndarray
    inlier: np.ndarray


@dataclass(frozen=True)
class Reconstruction:
    """Result of ``reconstruct``.

    poses : frame -> (R (3, 3), C (3,)), ``X_cam = R (X - C)``, registered frames only.
    points : (P, 3) float64 world points; point_track : (P,) int64 their track ids.
    camera : the adjusted shared camera (``distort_ideal``).
    residuals : per observation, see ObservationResiduals.
    gcp_positions : GCP id -> (3,) adjusted (controls, tie points) or triangulated (checkpoints) position.
    report : JSON-serialisable summary (see ``reconstruct``).
    """

    poses: dict[int, tuple[np.ndarray, np.ndarray]]
    points: np.ndarray
    point_track: np.ndarray
    camera: Camera
    residuals: ObservationResiduals
    gcp_positions: dict[str, np.ndarray]
    report: dict[str, Any]


# -- the pipeline --------------------------------------------------------------------------------------
def reconstruct(
    features: Sequence[np.ndarray],
    matches: PairMatches,
    camera: Camera,
    *,
    gps: Mapping[int, GpsFix] | None = None,
    attitude: Mapping[int, Attitude] | None = None,
    gcps: Sequence[GroundControlPoint] = (),
    checkpoints: Collection[str] = (),
    frame_names: Sequence[str] | None = None,
    options: ReconstructionOptions = ReconstructionOptions(),
) -> Reconstruction:
    """Camera poses, sparse points and the adjusted camera of one flight.

    Parameters
    ----------
    features : per frame ``i`` (N_i, 2) float pixel (x, y), OpenCV convention, in the pixel frame of ``camera``.
    matches : (i, j) -> (features of i, features of j), two (M,) int arrays of feature indices.
    camera : initial intrinsics shared by all frames (either convention; adjusted as ``distort_ideal``).
    gps : frame -> GpsFix, local-frame metres (``gcp.LocalFrame``), for any subset of frames.
    attitude : frame -> Attitude (DJI gimbal angles); used with ``gps`` when every frame has both (and the
        cameras they give fit the matches; otherwise the reconstruction starts incrementally).
    gcps : ground control points; observations keyed by image name (``frame_names``), same pixel frame.
    checkpoints : ids of GCPs held out of the adjustment and only compared with their triangulation.
    frame_names : name of each frame (for GCP observations and the report); default "0", "1", ...

    Returns
    -------
    Reconstruction. With fewer than two frames that can be registered, no poses and a report saying why.
    ``report`` keys: frames {total, registered, not_registered {name: reason}}, world_frame, initialisation,
    datum, points, observations, rejected_observations, rms_reprojection_px (root mean square length of
    the kept residual vectors), per_frame {name: {rms_px, observations, gps_residual_m,
    gps_residual_enu_m}}, gcps {id: {role, observations, rms_px, residual_m, residual_enu_m}},
    checkpoint_rmse_m, camera (``Camera.to_json``), adjustments, seconds, notes. GPS and GCP metres only
    in a world frame. Raises ValueError for frames, features or fixes that do not exist.
    """
    started = time.perf_counter()
    _check_inputs(features, matches, gps, attitude, frame_names)
    n = len(features)
    names = list(frame_names) if frame_names is not None else [str(i) for i in range(n)]
    camera = camera.with_convention("distort_ideal")
    normalised = [camera.pixel_to_normalised(np.asarray(f, dtype=np.float64)) for f in features]
    verified, essential = verify_pairs(
        normalised, matches, camera.fx, options.verify_threshold_px, options.min_pair_inliers
    )
    state = _new_state(build_tracks(verified, options.min_track_length), features, normalised)
    state.pairs, state.essential, state.normalised = verified, essential, normalised
    priors = Priors(dict(gps or {}), list(gcps), observations_by_frame(gcps, names), frozenset(checkpoints), camera.fx)
    log: list[dict] = []
    seeded = _seed(state, camera, options, priors, attitude or {}, log)
    if state.registered.sum() < 2:
        return _empty(state, camera, names, seeded, started)
    camera = _grow(state, camera, options, priors, log)
    _complete(state, camera, options)
    if state.world:  # seeded on GPS + attitude: settle the gauge the weak GPS priors leave loose (the fit to GPS)
        to_world(state, camera, priors, options)
        datum = DATUM_GPS_ATTITUDE
    else:
        datum = to_world(state, camera, priors, options)
    camera = _adjust_until_settled(state, camera, options, priors, log)
    camera = _recheck_frames(state, camera, options, priors, log)
    return _result(
        state,
        camera,
        priors,
        names,
        {"initialisation": seeded, "datum": datum, "log": log, "seconds": time.perf_counter() - started},
    )


def _seed(
    state: ReconstructionState,
    camera: Camera,
    options: ReconstructionOptions,
    priors: Priors,
    attitude: Mapping[int, Attitude],
    log: list,
) -> str:
    """Register the first frames: from GPS + attitude, or the best initial pair. Returns the method."""
    n = len(state.registered)
    full = all(f in attitude and f in priors.gps for f in range(n))
    if (options.initial == "attitude" or (options.initial == "auto" and full)) and _seed_attitude(
        state, camera, options, priors, attitude, log
    ):
        return DATUM_GPS_ATTITUDE
    pair = initial_pair(
        state.pairs,
        state.essential,
        state.normalised,
        options.min_pair_inliers,
        options.min_angle_deg,
        options.init_angle_deg,
    )
    if pair is None:
        return "incremental: no pair with enough inliers and baseline"
    i, j, R, t = pair
    state.rvecs[j], state.centres[j] = cv2.Rodrigues(R)[0].ravel(), -R.T @ t
    state.registered[[i, j]] = True
    state.gauge = (i, j)
    triangulate_tracks(
        state, camera, np.ones(len(state.has_point), bool), options.outlier_threshold_px, options.min_angle_deg
    )
    log.append(adjust_state(state, camera, options, priors, self_calibrate=False)[1])
    return f"incremental from frames {i} and {j}"


def _seed_attitude(
    state: ReconstructionState,
    camera: Camera,
    options: ReconstructionOptions,
    priors: Priors,
    attitude: Mapping[int, Attitude],
    log: list,
) -> bool:
    """Cameras straight from GPS + attitude, then an adjustment. Each frame's attitude is first checked against
    its pairs' relative poses in both heading conventions (``priors.check_attitude_priors``); a frame whose
    prior fits neither is left for PnP (``_grow``). False, with the state reset, when the kept metadata poses
    triangulate under a quarter of the tracks seen twice: the caller then starts incrementally."""
    check = check_attitude_priors(_pair_poses(state), attitude, priors.gps)
    for f, R in check.rotations.items():
        if f in priors.gps:
            state.rvecs[f] = vector_from_rotation(R)
            state.centres[f], state.registered[f] = priors.gps[f].position, True
    state.attitude = {**check.conventions, **{f: f"not used: {why}" for f, why in check.rejected.items()}}
    tr = state.tracks
    seen_twice = int((np.bincount(tr.track[state.registered[tr.frame]], minlength=len(state.has_point)) >= 2).sum())
    loose = 0.05 * max(camera.width, camera.height)  # metadata poses are a few degrees off
    if triangulate_tracks(
        state, camera, np.ones(len(state.has_point), bool), loose, options.min_angle_deg
    ) < 0.25 * max(seen_twice, 1):
        state.notes.append(
            "GPS + attitude cameras do not fit the matches (attitude convention?): started incrementally instead"
        )
        state.registered[:], state.has_point[:], state.active[:] = False, False, True
        state.rvecs[:], state.centres[:] = 0.0, 0.0
        state.attitude = {}
        return False
    if check.rejected:
        state.notes.append(f"attitude of {len(check.rejected)} frame(s) disagrees with their matches: placed by PnP")
    if len(set(check.conventions.values())) > 1:
        state.notes.append("the flight mixes heading conventions (the camera heading at yaw, and at yaw + 180)")
    state.world = True
    log.append(adjust_state(state, camera, options, priors, self_calibrate=False)[1])
    return True


def _grow(
    state: ReconstructionState, camera: Camera, options: ReconstructionOptions, priors: Priors, log: list
) -> Camera:
    """Register frames by PnP (else by relative pose), most 2D-3D matches first; adjust whenever the model
    grows by a quarter. A frame that fails is tried again once its matches to the model grow by a quarter. When
    no frame is left to try, the tracks reaching the frames left are triangulated again at half the minimum
    angle: along a street the few tracks that link the rest of a sequence may see too little parallax in the
    frames registered (lund's last five frames, when one pose came out 1e-9 different under OpenCV 5.1's
    refinement and frame 24.jpg was registered by PnP instead of by relative pose)."""
    tr = state.tracks
    tried: dict[int, int] = {}
    last = int(state.registered.sum())
    while True:
        live = state.active & state.has_point[tr.track] & ~state.registered[tr.frame]
        counts = np.bincount(tr.frame[live], minlength=len(state.registered))
        todo = [
            int(f)
            for f in np.flatnonzero(~state.registered)
            if counts[f] >= 3 and counts[f] > 1.25 * tried.get(int(f), 0)
        ]
        if not todo:
            # stalled: the tracks that reach the frames left may see too little parallax in the registered
            # frames (forward motion along a street); triangulate them at half the angle and go on
            stalled = np.zeros(len(state.has_point), bool)
            stalled[tr.track[~state.registered[tr.frame]]] = True
            if triangulate_tracks(state, camera, stalled, options.outlier_threshold_px, options.min_angle_deg / 2):
                continue
            for f in np.flatnonzero(~state.registered):
                state.reasons.setdefault(int(f), f"only {counts[f]} matches to reconstructed points")
            break
        frame = int(max(todo, key=lambda f: counts[f]))
        tried[frame] = int(counts[frame])
        why = register_by_pnp(state, frame, camera, options.min_pnp_inliers, options.pnp_threshold_px)
        if why:
            why = register_by_relative_pose(state, frame) and why  # the PnP reason when both fail
        if why:
            state.reasons[frame] = why
            continue
        state.reasons.pop(frame, None)
        seen = np.zeros(len(state.has_point), bool)
        seen[tr.track[tr.frame == frame]] = True
        triangulate_tracks(state, camera, seen, options.outlier_threshold_px, options.min_angle_deg)
        if state.registered.sum() >= 1.25 * last:
            last = int(state.registered.sum())
            camera, stats = adjust_state(state, camera, options, priors, self_calibrate=False)
            log.append(stats)
    return camera


def _adjust_until_settled(
    state: ReconstructionState, camera: Camera, options: ReconstructionOptions, priors: Priors, log: list
) -> Camera:
    """Adjust with self-calibration, then re-admit what now fits, until little changes (at most three times,
    as COLMAP's global loop)."""
    for _ in range(3):
        camera, stats = adjust_state(state, camera, options, priors, self_calibrate=True)
        log.append(stats)
        if _complete(state, camera, options) < 0.02 * state.active.sum():
            break
    return camera


def _pair_poses(state: ReconstructionState) -> dict[tuple[int, int], tuple[np.ndarray, np.ndarray]]:
    """Every verified pair's relative pose from its essential matrix: (R, t) with ``X_j = R X_i + t``."""
    out = {}
    for (i, j), (fi, fj) in state.pairs.items():
        R, t, _, _ = relative_pose(state.essential[(i, j)], state.normalised[i][fi], state.normalised[j][fj])
        out[(i, j)] = (R, t)
    return out


def _misfits(state: ReconstructionState, priors: Priors, options: ReconstructionOptions) -> dict[int, tuple[str, str]]:
    """Registered frames the adjustment holds on too few observations (fewer than ``min_pnp_inliers``, or under
    a tenth of the tie points their pairs offered), or far from their GPS fix (beyond ``GPS_MISFIT_SIGMAS`` of
    its horizontal accuracy): frame -> (kind, why), kind "starved" or "gps"."""
    kept, offered = frame_observations(state)
    out = {}
    for f in map(int, np.flatnonzero(state.registered)):
        need = max(options.min_pnp_inliers, int(MIN_KEPT_SHARE * offered[f]))
        if kept[f] < need:
            out[f] = (
                "starved",
                f"the adjustment kept {kept[f]} of the {offered[f]} tie points its pairs offered (needs {need})",
            )
        elif (miss := _gps_miss_m(state, priors, f)) is not None and miss > GPS_MISFIT_SIGMAS * priors.gps[f].sigma_h:
            out[f] = (
                "gps",
                f"its camera lies {miss:.1f} m from its GPS position (accuracy {priors.gps[f].sigma_h:g} m)",
            )
    return out


def _gps_miss_m(state: ReconstructionState, priors: Priors, f: int) -> float | None:
    """Horizontal distance (m) of frame ``f``'s camera from its GPS fix; None without a fix or a world frame."""
    if not state.world or f not in priors.gps:
        return None
    return float(np.linalg.norm((state.centres[f] - np.asarray(priors.gps[f].position))[:2]))


def _recheck_frames(
    state: ReconstructionState, camera: Camera, options: ReconstructionOptions, priors: Priors, log: list
) -> Camera:
    """Outlier rejection never empties a frame silently: every misfit frame (``_misfits``) is taken out and
    placed again from the rest of the model by PnP on its tracks (else by its relative pose), and the model
    adjusted again, twice at most; a frame that still keeps too few observations is left out (not registered,
    with the reason); one that fits its matches but not its GPS stays, and the report says so."""
    tr = state.tracks
    for _ in range(2):
        bad = {f: why for f, (_, why) in _misfits(state, priors, options).items()}
        if not bad:
            return camera
        unregister(state, list(bad))
        # tracks the misfits spoiled (their wrong rays failed the triangulation) from the frames that remain
        state.active[~state.has_point[tr.track]] = True
        triangulate_tracks(state, camera, ~state.has_point, options.outlier_threshold_px, options.min_angle_deg)
        for f in sorted(bad, key=lambda f: -int(np.sum(tr.frame == f))):
            why = register_by_pnp(state, f, camera, options.min_pnp_inliers, options.pnp_threshold_px)
            if why:
                why = register_by_relative_pose(state, f) and why
            if why:
                state.reasons[f] = f"{bad[f]}; placing it again failed: {why}"
                continue
            state.reinitialised[f] = bad[f]
            seen = np.zeros(len(state.has_point), bool)
            seen[tr.track[tr.frame == f]] = True
            triangulate_tracks(state, camera, seen, options.outlier_threshold_px, options.min_angle_deg)
        camera = _adjust_until_settled(state, camera, options, priors, log)
    still = {f: why for f, (kind, why) in _misfits(state, priors, options).items() if kind == "starved"}
    if still:
        unregister(state, list(still))
        state.reasons.update({f: f"{why}, also after it was placed again" for f, why in still.items()})
    return camera


def _complete(state: ReconstructionState, camera: Camera, options: ReconstructionOptions) -> int:
    """Give rejected observations a second chance against the current model (they were judged with
    rougher cameras), then triangulate every track that can be and refine all points. Returns how many
    observations joined the model."""
    tr = state.tracks
    before = int((state.active & state.has_point[tr.track] & state.registered[tr.frame]).sum())
    state.active[~state.has_point[tr.track]] = True
    sel = np.flatnonzero(state.has_point[tr.track] & ~state.active & state.registered[tr.frame])
    R, C = state_rotations(state)[tr.frame[sel]], state.centres[tr.frame[sel]]
    fits = reprojection_errors(camera, R, C, state.points[tr.track[sel]], state.xy[sel]) <= options.outlier_threshold_px
    state.active[sel[fits]] = True
    triangulate_tracks(
        state, camera, np.ones(len(state.has_point), bool), options.outlier_threshold_px, options.min_angle_deg
    )
    refine_all_points(state, camera, options.outlier_threshold_px)
    return int((state.active & state.has_point[tr.track] & state.registered[tr.frame]).sum()) - before


def _new_state(tracks: Tracks, features: Sequence[np.ndarray], normalised: Sequence[np.ndarray]) -> ReconstructionState:
    n = len(features)
    xy = np.array([features[f][k] for f, k in zip(tracks.frame, tracks.feature, strict=True)]).reshape(-1, 2)
    ideal = np.array([normalised[f][k] for f, k in zip(tracks.frame, tracks.feature, strict=True)]).reshape(-1, 2)
    return ReconstructionState(
        tracks,
        xy.astype(np.float64),
        np.column_stack([ideal, np.ones(len(ideal))]),
        np.zeros((n, 3)),
        np.zeros((n, 3)),
        np.zeros(n, bool),
        np.zeros((tracks.n_tracks, 3)),
        np.zeros(tracks.n_tracks, bool),
        np.ones(len(tracks.track), bool),
    )


def _check_inputs(
    features: Sequence[np.ndarray],
    matches: PairMatches,
    gps: Mapping | None,
    attitude: Mapping | None,
    names: Sequence[str] | None,
) -> None:
    n = len(features)
    if any(np.ndim(f) != 2 or np.shape(f)[1] != 2 for f in features):
        raise ValueError("features must be one (N_i, 2) array of pixel (x, y) per frame")
    if names is not None and len(names) != n:
        raise ValueError(f"frame_names has {len(names)} names for {n} frames")
    for (i, j), (fi, fj) in matches.items():
        if not (0 <= i < n and 0 <= j < n):
            raise ValueError(f"pair {(i, j)} refers to a frame outside 0..{n - 1}")
        if len(fi) and (np.max(fi) >= len(features[i]) or np.max(fj) >= len(features[j])):
            raise ValueError(f"pair {(i, j)} refers to a feature index beyond its frame's features")
    for what, table in (("gps", gps or {}), ("attitude", attitude or {})):
        if any(not 0 <= f < n for f in table):
            raise ValueError(f"{what} refers to a frame outside 0..{n - 1}")


# -- results -------------------------------------------------------------------------------------------
def _result(state: ReconstructionState, camera: Camera, priors: Priors, names: list[str], info: dict) -> Reconstruction:
    tr = state.tracks
    out = np.flatnonzero(state.has_point)
    row = np.full(len(state.has_point), -1)
    row[out] = np.arange(len(out))
    sel = state.has_point[tr.track] & state.registered[tr.frame]
    frames = tr.frame[sel]
    cam = np.einsum("kij,kj->ki", state_rotations(state)[frames], state.points[tr.track[sel]] - state.centres[frames])
    residuals = ObservationResiduals(
        frames, row[tr.track[sel]], state.xy[sel], camera.project(cam) - state.xy[sel], state.active[sel]
    )
    poses = {int(f): (state_rotations(state)[f], state.centres[f].copy()) for f in np.flatnonzero(state.registered)}
    triangulated = gcps_triangulated(state, camera, priors)
    gcp_report, positions = report_gcps(
        priors.gcps,
        priors.gcp_obs,
        priors.checkpoints,
        state.registered,
        info["log"][-1]["gcp"],
        triangulated,
        state.world,
    )
    inl = residuals.inlier
    report = {
        "frames": _frames_report(state, names),
        "world_frame": "local (E - E0, N - N0, height) metres"
        if state.world
        else "arbitrary: scale set by the initial pair's baseline = 1",
        "initialisation": info["initialisation"],
        "datum": info["datum"],
        "points": len(out),
        "observations": int(inl.sum()),
        "rejected_observations": int((~inl).sum()),
        "rms_reprojection_px": _num(bundle.rms(residuals.residual[inl])),
        "per_frame": _per_frame(state, priors, names, residuals),
        "warnings": _warnings(state, priors, names),
        "gcps": gcp_report,
        "checkpoint_rmse_m": checkpoint_rmse(gcp_report),
        "camera": camera.to_json(),
        "adjustments": [{k: v for k, v in s.items() if k != "gcp"} for s in info["log"]],
        "seconds": round(info["seconds"], 3),
        "notes": state.notes,
    }
    return Reconstruction(poses, state.points[out], out.astype(np.int64), camera, residuals, positions, report)


def _frames_report(state: ReconstructionState, names: list[str]) -> dict:
    missing = {
        names[f]: state.reasons.get(int(f), "no verified matches to the registered frames")
        for f in np.flatnonzero(~state.registered)
    }
    return {"total": len(names), "registered": int(state.registered.sum()), "not_registered": missing}


def _per_frame(state: ReconstructionState, priors: Priors, names: list[str], residuals: ObservationResiduals) -> dict:
    """Per registered frame: its observations and the tie points its pairs offered, RMS, GPS residual, how its
    attitude prior was read and whether it had to be placed again."""
    by_frame = bundle.rms_by_group(residuals.residual[residuals.inlier], residuals.frame[residuals.inlier])
    _, offered = frame_observations(state)
    out: dict[str, dict] = {}
    for f in map(int, np.flatnonzero(state.registered)):
        rms_px, count = by_frame.get(f, (float("nan"), 0))
        entry: dict[str, Any] = {
            "rms_px": _num(rms_px),
            "observations": count,
            "tie_points_offered": int(offered[f]),
            "status": IMAGE_STATUSES[1] if f in state.reinitialised else IMAGE_STATUSES[0],
        }
        if f in state.attitude:
            entry["attitude"] = state.attitude[f]
        if state.world and f in priors.gps:
            enu = state.centres[f] - np.asarray(priors.gps[f].position)
            entry.update(gps_residual_m=_num(float(np.linalg.norm(enu))), gps_residual_enu_m=[_num(v) for v in enu])
        out[names[f]] = entry
    return out


def _warnings(state: ReconstructionState, priors: Priors, names: list[str]) -> list[str]:
    """What a user must know before trusting the result, in words: frames left out, frames placed again, and
    cameras further from their GPS fixes than the GPS accuracy allows."""
    out = []
    missing = [names[f] for f in np.flatnonzero(~state.registered)]
    if missing:
        out.append(f"{len(missing)} of {len(names)} frames could not be placed and are left out: {', '.join(missing)}")
    for f, why in sorted(state.reinitialised.items()):
        if state.registered[f]:
            out.append(f"{names[f]} was placed again after the adjustment ({why})")
    if state.world:
        far = []
        for f in map(int, np.flatnonzero(state.registered)):
            if (miss := _gps_miss_m(state, priors, f)) is not None and miss > GPS_WARNING_SIGMAS * priors.gps[
                f
            ].sigma_h:
                far.append(f"{names[f]} {miss:.1f} m")
        if far:
            sigma = max(priors.gps[f].sigma_h for f in priors.gps)
            out.append(
                f"{len(far)} camera(s) lie further from their GPS positions than {GPS_WARNING_SIGMAS:g} x the "
                f"GPS accuracy ({sigma:g} m): {', '.join(far)}"
            )
    return out


def _empty(state: ReconstructionState, camera: Camera, names: list[str], seeded: str, started: float) -> Reconstruction:
    for f in range(len(names)):
        state.reasons.setdefault(f, seeded)
    state.registered[:] = False
    z = np.zeros(0, np.int64)
    residuals = ObservationResiduals(z, z, np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0, bool))
    report = {
        "frames": _frames_report(state, names),
        "initialisation": seeded,
        "points": 0,
        "rms_reprojection_px": None,
        "seconds": round(time.perf_counter() - started, 3),
        "notes": state.notes,
    }
    return Reconstruction({}, np.zeros((0, 3)), z, camera, residuals, {}, report)


def _num(value: float) -> float | None:
    """A JSON-safe float (None for NaN), rounded to 6 decimals."""
    value = float(value)
    return None if not np.isfinite(value) else round(value, 6)
