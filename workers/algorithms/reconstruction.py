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
from dataclasses import dataclass, field, replace
from typing import Any, Literal

import cv2
import numpy as np

from workers.algorithms import bundle
from workers.algorithms.camera import Camera, vector_from_rotation
from workers.algorithms.datum import (
    Attitude,
    GpsFix,
    checkpoint_rmse,
    control_layout,
    line_similarity,
    observations_by_frame,
    refine_similarity,
    report_gcps,
    rotation_from_attitude,
    similarity_3d,
    triangulate_gcps,
)
from workers.algorithms.gcp import GroundControlPoint
from workers.algorithms.matching import spread_subset
from workers.algorithms.tracks import PairMatches, Tracks, build_tracks, initial_pair, relative_pose, verify_pairs


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


@dataclass
class _State:
    """The growing model; track observations are rows k of ``tracks``."""

    tracks: Tracks
    xy: np.ndarray  # (K, 2) observed px
    ray: np.ndarray  # (K, 3) ideal normalised (x, y, 1) in the camera
    rvecs: np.ndarray  # (F, 3)
    centres: np.ndarray  # (F, 3)
    registered: np.ndarray  # (F,) bool
    points: np.ndarray  # (T, 3)
    has_point: np.ndarray  # (T,) bool
    active: np.ndarray  # (K,) bool: not rejected
    pairs: dict = field(default_factory=dict)  # verified matches (i, j) -> (features_i, features_j)
    essential: dict = field(default_factory=dict)  # (i, j) -> (3, 3)
    normalised: Sequence[np.ndarray] = ()  # per frame (N_i, 2) ideal normalised features
    world: bool = False
    gauge: tuple[int, int] | None = None
    reasons: dict[int, str] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)


# -- triangulation and registration ---------------------------------------------------------------------
def _rotations(state: _State) -> np.ndarray:
    return bundle.rotations_from_vectors(state.rvecs)


def _triangulate(state: _State, camera: Camera, wanted: np.ndarray, max_error_px: float,
                 min_angle_deg: float) -> int:
    """Triangulate tracks ``wanted`` (T,) bool from their active observations in registered frames;
    observations beyond ``max_error_px`` are dropped and the track tried once more. Returns points made."""
    made = 0
    for _ in range(2):
        tr = state.tracks
        sel = wanted[tr.track] & ~state.has_point[tr.track] & state.active & state.registered[tr.frame]
        if not sel.any():
            break
        ids, group = np.unique(tr.track[sel], return_inverse=True)
        frames, R = tr.frame[sel], _rotations(state)[tr.frame[sel]]
        C = state.centres[frames]
        d = np.einsum("kji,kj->ki", R, state.ray[sel])  # R^T ray: world direction
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        X, solved = bundle.triangulate_rays(C, d, group, len(ids))
        X = bundle.refine_points(camera, R, C, state.xy[sel], group, X, iterations=3)
        bad_obs = ~(_errors(camera, R, C, X[group], state.xy[sel]) <= max_error_px)
        ok = solved & (np.bincount(group, weights=bad_obs, minlength=len(ids)) == 0)
        ok &= _max_angle(d, group, len(ids)) >= np.radians(min_angle_deg)
        state.points[ids[ok]], state.has_point[ids[ok]] = X[ok], True
        made += int(ok.sum())
        state.active[np.flatnonzero(sel)[bad_obs & solved[group]]] = False  # then retry without them
    return made


def _errors(camera: Camera, R: np.ndarray, C: np.ndarray, X: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """(K,) reprojection error px of points X (K, 3) seen by cameras (R, C); inf behind a camera or unsolved."""
    cam = np.einsum("kij,kj->ki", R, np.nan_to_num(X, nan=0.0) - C)
    front = (cam[:, 2] > 1e-9) & np.all(np.isfinite(X), axis=1)
    err = np.full(len(cam), np.inf)
    err[front] = np.linalg.norm(camera.project(cam[front]) - xy[front], axis=1)
    return err


def _max_angle(d: np.ndarray, group: np.ndarray, n: int) -> np.ndarray:
    """Per group, the largest angle (rad) between a ray and the group's first ray (at least half
    the largest pairwise angle)."""
    first = np.full(n, -1)
    first[group[::-1]] = np.arange(len(group))[::-1]
    cos = np.clip(np.sum(d * d[first[group]], axis=1), -1.0, 1.0)
    angle = np.zeros(n)
    np.maximum.at(angle, group, np.arccos(cos))
    return angle


def _register(state: _State, frame: int, camera: Camera, options: ReconstructionOptions) -> str | None:
    """Pose of ``frame`` by PnP RANSAC + Levenberg-Marquardt refinement; None on success, else why not."""
    tr = state.tracks
    sel = np.flatnonzero((tr.frame == frame) & state.has_point[tr.track] & state.active)
    if len(sel) < options.min_pnp_inliers:
        return f"only {len(sel)} matches to reconstructed points (needs {options.min_pnp_inliers})"
    K = camera.matrix()
    obj, img = state.points[tr.track[sel]], state.ray[sel, :2] * [camera.fx, camera.fy] + [camera.cx, camera.cy]
    cv2.setRNGSeed(len(sel))
    ok, rvec, tvec, inl = cv2.solvePnPRansac(obj, img, K, None, iterationsCount=1000, confidence=0.9999,
                                             reprojectionError=options.pnp_threshold_px, flags=cv2.SOLVEPNP_SQPNP)
    n_in = 0 if inl is None else len(inl)
    if not ok or n_in < options.min_pnp_inliers:
        return f"PnP found {n_in} inliers among {len(sel)} matches to reconstructed points"
    inl = inl.ravel()
    rvec, tvec = cv2.solvePnPRefineLM(obj[inl], img[inl], K, None, rvec, tvec)
    R = cv2.Rodrigues(rvec)[0]
    state.rvecs[frame], state.centres[frame] = rvec.ravel(), -R.T @ tvec.ravel()
    state.registered[frame] = True
    outlier = np.ones(len(sel), bool)
    outlier[inl] = False
    state.active[sel[outlier]] = False
    return None


def _register_relative(state: _State, frame: int, options: ReconstructionOptions) -> str | None:
    """Fallback for a frame PnP cannot place (few tracks reach it, as on a weakly linked street
    sequence): its relative pose to the registered frame it shares most verified matches with (that
    pair's essential matrix), scaled by the median depth ratio of the reconstructed points both see."""
    links = [(len(m[0]), p) for p, m in state.pairs.items() if frame in p and state.registered[p[0] + p[1] - frame]]
    if not links:
        return "no verified pair with a registered frame"
    i, j = max(links)[1]
    r = i + j - frame
    fi, fj = state.pairs[(i, j)]
    xi, xj = state.normalised[i][fi], state.normalised[j][fj]
    R, t, unit, ok = relative_pose(state.essential[(i, j)], xi, xj)
    depth_unit = unit[:, 2] if r == i else (unit @ R.T + t)[:, 2]
    row_of = np.full(len(state.normalised[r]), -1)
    rows_r = np.flatnonzero((state.tracks.frame == r) & state.active)
    row_of[state.tracks.feature[rows_r]] = rows_r
    k = row_of[fi if r == i else fj]
    use = ok & (k >= 0) & (depth_unit > 0)
    use[use] &= state.has_point[state.tracks.track[k[use]]]
    Rr = _rotations(state)[r]
    depth = (state.points[state.tracks.track[k[use]]] - state.centres[r]) @ Rr[2]
    ratio = depth / depth_unit[use]
    if np.sum(ratio > 0) < 3:
        return "relative pose: fewer than 3 reconstructed points to scale it"
    s = float(np.median(ratio[ratio > 0]))
    Rf = R @ Rr if r == i else R.T @ Rr
    state.centres[frame] = state.centres[r] - s * Rf.T @ t if r == i else state.centres[r] + s * Rr.T @ t
    state.rvecs[frame], state.registered[frame] = vector_from_rotation(Rf), True
    state.notes.append(f"frame {frame} placed by its relative pose to frame {r} ({int(use.sum())} points for scale)")
    return None


# -- bundle adjustment of the state ---------------------------------------------------------------------
@dataclass(frozen=True)
class _Priors:
    """World-frame measurements: GPS fixes and GCPs, already mapped to frame indices."""

    gps: Mapping[int, GpsFix]
    gcps: Sequence[GroundControlPoint]
    gcp_obs: list[tuple[int, int, np.ndarray]]  # (gcp index, frame, (2,) px)
    checkpoints: frozenset[str]
    focal: float  # the initial focal length, px


def _ba_points(state: _State, camera: Camera, per_frame: int) -> np.ndarray:
    """(T,) bool: a subset of the points that gives every frame about ``per_frame`` of them, spread over
    the image, long tracks first (points chosen for one frame count for the others that see them)."""
    tr = state.tracks
    usable = state.has_point[tr.track] & state.active & state.registered[tr.frame]
    length = np.bincount(tr.track[usable], minlength=len(state.has_point))
    chosen = np.zeros(len(state.has_point), bool)
    for frame in np.flatnonzero(state.registered):
        rows = np.flatnonzero(usable & (tr.frame == frame))
        need = per_frame - int(chosen[tr.track[rows]].sum())
        rows = rows[~chosen[tr.track[rows]]]
        long = rows[length[tr.track[rows]] >= 3]
        rows = long if len(long) >= need else rows
        if need > 0 and len(rows):
            pick = spread_subset(state.xy[rows], (camera.width, camera.height), need, seed=int(frame))
            chosen[tr.track[rows[pick]]] = True
    return chosen


def _adjust(state: _State, camera: Camera, options: ReconstructionOptions, priors: _Priors,
            self_calibrate: bool) -> tuple[Camera, dict]:
    """Bundle-adjust registered frames and a subset of points (+ GCPs), then refine every other point
    with the cameras held and drop observations beyond the outlier threshold."""
    frames = np.flatnonzero(state.registered)
    row_of = np.full(len(state.registered), -1)
    row_of[frames] = np.arange(len(frames))
    ids = np.flatnonzero(_ba_points(state, camera, options.ba_points_per_frame))
    tr = state.tracks
    point_row = np.full(len(state.has_point), -1)
    point_row[ids] = np.arange(len(ids))
    obs = np.flatnonzero((point_row[tr.track] >= 0) & state.active & state.registered[tr.frame])
    problem = bundle.BundleProblem(camera, state.rvecs[frames], state.centres[frames], state.points[ids],
                                   row_of[tr.frame[obs]], point_row[tr.track[obs]], state.xy[obs])
    problem, gcp_ids = _with_world_terms(problem, state, row_of, priors, options, camera)
    problem = replace(problem, focal_prior=(priors.focal, options.focal_sigma * priors.focal))
    flags = dict(refine_focal=options.refine_focal, refine_k1=options.refine_k1, refine_k2=options.refine_k2)
    bopts = bundle.BundleOptions(options.loss, options.loss_scale_px, options.outlier_threshold_px,
                                 max_nfev=options.max_nfev, **(flags if self_calibrate else {}))
    started = time.perf_counter()
    result = bundle.adjust(problem, bopts)
    state.rvecs[frames], state.centres[frames] = result.rvecs, result.centres
    state.points[ids] = result.points[: len(ids)]
    state.active[obs[~result.inlier[: len(obs)]]] = False
    _refine_all_points(state, result.camera, options.outlier_threshold_px)
    stats = {"frames": len(frames), "points": len(ids), "observations": len(obs), "nfev": result.nfev,
             "seconds": round(time.perf_counter() - started, 3),
             "gcp": {gid: (result.points[len(ids) + k], result.residuals[len(obs):][problem.obs_point[len(obs):]
                                                                                    == len(ids) + k])
                     for k, gid in enumerate(gcp_ids)}}
    return result.camera, stats


def _with_world_terms(problem: bundle.BundleProblem, state: _State, row_of: np.ndarray, priors: _Priors,
                      options: ReconstructionOptions, camera: Camera) -> tuple[bundle.BundleProblem, list[str]]:
    """Add GPS priors and GCP points / observations / priors, or the gauge of an arbitrary frame."""
    if not state.world:
        a, b = state.gauge if state.gauge else (int(np.flatnonzero(state.registered)[0]),) * 2
        return replace(problem, fixed_frames=np.array([row_of[a]]),
                       gauge_pair=(int(row_of[a]), int(row_of[b])) if a != b else None), []
    gps = [f for f in sorted(priors.gps) if row_of[f] >= 0]
    fixes = [priors.gps[f] for f in gps]
    gps_xyz = np.array([g.position for g in fixes]).reshape(-1, 3)
    sigma = np.array([[g.sigma_h, g.sigma_h, g.sigma_v] for g in fixes]).reshape(-1, 3)
    gcp_xyz, gcp_ids, rows, xy, prior_rows = _gcp_terms(state, camera, row_of, priors, len(problem.points))
    fixed_rot = np.zeros(0, np.int64)
    if len(gps) and not prior_rows and control_layout(gps_xyz, float(np.median(sigma[:, 0]))) == "line":
        fixed_rot = np.array([row_of[gps[len(gps) // 2]]])  # the turn about the line is not observable
    prior_xyz = gcp_xyz[np.asarray(prior_rows, dtype=np.int64) - len(problem.points)]
    protected = np.r_[np.zeros(len(problem.obs_frame), bool), np.ones(len(rows), bool)]
    return replace(problem, points=np.vstack([problem.points, gcp_xyz]),
                   obs_frame=np.r_[problem.obs_frame, np.asarray([r[0] for r in rows], dtype=np.int64)],
                   obs_point=np.r_[problem.obs_point, np.asarray([r[1] for r in rows], dtype=np.int64)],
                   obs_xy=np.vstack([problem.obs_xy, np.asarray(xy).reshape(-1, 2)]),
                   gps_frame=row_of[np.asarray(gps, dtype=np.int64)], gps_xyz=gps_xyz, gps_sigma=sigma,
                   prior_point=np.asarray(prior_rows, dtype=np.int64), prior_xyz=prior_xyz.reshape(-1, 3),
                   prior_sigma=np.full(len(prior_rows), options.gcp_sigma_m), fixed_rotations=fixed_rot,
                   protected=protected), gcp_ids


def _gcp_terms(state: _State, camera: Camera, row_of: np.ndarray, priors: _Priors, first_row: int) -> tuple:
    """GCPs in the adjustment: controls (known position, a prior) and tie points (two views or more)."""
    xyz: list[np.ndarray] = []
    ids: list[str] = []
    rows: list[tuple[int, int]] = []
    xy: list[np.ndarray] = []
    prior_rows: list[int] = []
    triangulated = _gcps_triangulated(state, camera, priors)
    for g, gcp in enumerate(priors.gcps):
        seen = [(f, p) for k, f, p in priors.gcp_obs if k == g and row_of[f] >= 0]
        control = gcp.position is not None and gcp.id not in priors.checkpoints
        if gcp.id in priors.checkpoints or not seen or (not control and gcp.id not in triangulated):
            continue
        row = first_row + len(ids)
        if control:
            prior_rows.append(row)
        xyz.append(gcp.position if control and gcp.position is not None else triangulated[gcp.id])
        ids.append(gcp.id)
        rows += [(int(row_of[f]), row) for f, _ in seen]
        xy += [p for _, p in seen]
    return np.asarray(xyz, dtype=np.float64).reshape(-1, 3), ids, rows, xy, prior_rows


def _gcps_triangulated(state: _State, camera: Camera, priors: _Priors) -> dict[str, np.ndarray]:
    return triangulate_gcps(camera, _rotations(state), state.centres, state.registered, priors.gcps, priors.gcp_obs)


def _refine_all_points(state: _State, camera: Camera, threshold_px: float) -> None:
    tr = state.tracks
    for _ in range(2):
        sel = np.flatnonzero(state.has_point[tr.track] & state.active & state.registered[tr.frame])
        R, C = _rotations(state)[tr.frame[sel]], state.centres[tr.frame[sel]]
        state.points = bundle.refine_points(camera, R, C, state.xy[sel], tr.track[sel], state.points, iterations=3)
        err = _errors(camera, R, C, state.points[tr.track[sel]], state.xy[sel])
        state.active[sel[err > threshold_px]] = False
    live = state.active & state.registered[tr.frame]
    state.has_point &= np.bincount(tr.track[live], minlength=len(state.has_point)) >= 2


# -- datum ---------------------------------------------------------------------------------------------
def _apply_similarity(state: _State, s: float, R: np.ndarray, t: np.ndarray) -> None:
    """Move the model: ``X' = s R X + t``; camera rotations become ``R_cam R^T``."""
    state.centres = s * state.centres @ R.T + t
    state.points = s * state.points @ R.T + t
    rot = _rotations(state) @ R.T
    state.rvecs = np.array([vector_from_rotation(r) for r in rot])


def _to_world(state: _State, camera: Camera, priors: _Priors, options: ReconstructionOptions) -> str:
    """Move an incremental model onto its control: a 3D similarity of camera centres and triangulated
    control points to the GPS fixes and known positions when these spread in 3D, else a line fit to the
    GPS fixes with level cameras (``datum.line_similarity``). Returns the method."""
    frames = [f for f in sorted(priors.gps) if state.registered[f]]
    known = {g.id: g.position for g in priors.gcps if g.position is not None and g.id not in priors.checkpoints}
    tri = {k: v for k, v in _gcps_triangulated(state, camera, priors).items() if k in known}
    gps = np.array([priors.gps[f].position for f in frames], dtype=np.float64).reshape(-1, 3)
    src = np.vstack([state.centres[frames], np.array(list(tri.values())).reshape(-1, 3)])
    dst = np.vstack([gps, np.array([known[k] for k in tri]).reshape(-1, 3)])
    sigma = float(np.median([priors.gps[f].sigma_h for f in frames])) if frames else options.gcp_sigma_m
    layout = control_layout(dst, sigma)
    if layout == "spread":
        fit = similarity_3d(src, dst)
    elif layout == "line" and len(frames) >= 2:
        fit = line_similarity(state.centres[frames], gps, _rotations(state)[frames])
    else:
        state.notes.append("GPS fixes and control points too few or too close together for their accuracy: "
                           "arbitrary frame, scale set by the initial baseline = 1")
        return "none"
    if tri:  # weigh GPS fixes and control points by their accuracy
        weights = np.r_[[priors.gps[f].sigma_h for f in frames], np.full(len(tri), options.gcp_sigma_m)]
        fit = refine_similarity(src, dst, weights, *fit)
    _apply_similarity(state, *fit)
    state.world = True
    return {"spread": "similarity_to_gps_and_gcps", "line": "gps_line_level_cameras"}[layout]


# -- the pipeline --------------------------------------------------------------------------------------
def reconstruct(features: Sequence[np.ndarray], matches: PairMatches, camera: Camera, *,
                gps: Mapping[int, GpsFix] | None = None, attitude: Mapping[int, Attitude] | None = None,
                gcps: Sequence[GroundControlPoint] = (), checkpoints: Collection[str] = (),
                frame_names: Sequence[str] | None = None,
                options: ReconstructionOptions = ReconstructionOptions()) -> Reconstruction:
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
    verified, essential = verify_pairs(normalised, matches, camera.fx, options.verify_threshold_px,
                                       options.min_pair_inliers)
    state = _new_state(build_tracks(verified, options.min_track_length), features, normalised)
    state.pairs, state.essential, state.normalised = verified, essential, normalised
    priors = _Priors(dict(gps or {}), list(gcps), observations_by_frame(gcps, names), frozenset(checkpoints),
                     camera.fx)
    log: list[dict] = []
    seeded = _seed(state, camera, options, priors, attitude or {}, log)
    if state.registered.sum() < 2:
        return _empty(state, camera, names, seeded, started)
    camera = _grow(state, camera, options, priors, log)
    _complete(state, camera, options)
    datum = "gps_attitude" if state.world else _to_world(state, camera, priors, options)
    for _ in range(3):  # adjust, then re-admit what now fits, until little changes (COLMAP's global loop)
        camera, final = _adjust(state, camera, options, priors, self_calibrate=True)
        log.append(final)
        if _complete(state, camera, options) < 0.02 * state.active.sum():
            break
    return _result(state, camera, priors, names, {"initialisation": seeded, "datum": datum, "log": log,
                                                  "seconds": time.perf_counter() - started})


def _seed(state: _State, camera: Camera, options: ReconstructionOptions, priors: _Priors,
          attitude: Mapping[int, Attitude], log: list) -> str:
    """Register the first frames: from GPS + attitude, or the best initial pair. Returns the method."""
    n = len(state.registered)
    full = all(f in attitude and f in priors.gps for f in range(n))
    if (options.initial == "attitude" or (options.initial == "auto" and full)) and _seed_attitude(
            state, camera, options, priors, attitude, log):
        return "gps_attitude"
    pair = initial_pair(state.pairs, state.essential, state.normalised, options.min_pair_inliers,
                        options.min_angle_deg, options.init_angle_deg)
    if pair is None:
        return "incremental: no pair with enough inliers and baseline"
    i, j, R, t = pair
    state.rvecs[j], state.centres[j] = cv2.Rodrigues(R)[0].ravel(), -R.T @ t
    state.registered[[i, j]] = True
    state.gauge = (i, j)
    _triangulate(state, camera, np.ones(len(state.has_point), bool), options.outlier_threshold_px,
                 options.min_angle_deg)
    log.append(_adjust(state, camera, options, priors, self_calibrate=False)[1])
    return f"incremental from frames {i} and {j}"


def _seed_attitude(state: _State, camera: Camera, options: ReconstructionOptions, priors: _Priors,
                   attitude: Mapping[int, Attitude], log: list) -> bool:
    """Cameras straight from GPS + attitude, then an adjustment. False, with the state reset, when the
    metadata poses triangulate under a quarter of the tracks seen twice (attitude in another convention,
    or wrong): the caller then starts incrementally."""
    for f in range(len(state.registered)):
        if f in attitude and f in priors.gps:
            state.rvecs[f] = vector_from_rotation(rotation_from_attitude(attitude[f]))
            state.centres[f], state.registered[f] = priors.gps[f].position, True
    tr = state.tracks
    seen_twice = int((np.bincount(tr.track[state.registered[tr.frame]], minlength=len(state.has_point)) >= 2).sum())
    loose = 0.05 * max(camera.width, camera.height)  # metadata poses are a few degrees off
    if _triangulate(state, camera, np.ones(len(state.has_point), bool), loose, options.min_angle_deg) < 0.25 * max(
            seen_twice, 1):
        state.notes.append("GPS + attitude cameras do not fit the matches (attitude convention?): started "
                           "incrementally instead")
        state.registered[:], state.has_point[:], state.active[:] = False, False, True
        state.rvecs[:], state.centres[:] = 0.0, 0.0
        return False
    state.world = True
    log.append(_adjust(state, camera, options, priors, self_calibrate=False)[1])
    return True


def _grow(state: _State, camera: Camera, options: ReconstructionOptions, priors: _Priors, log: list) -> Camera:
    """Register frames by PnP (else by relative pose), most 2D-3D matches first; adjust whenever the model
    grows by a quarter. A frame that fails is tried again once its matches to the model grow by a quarter."""
    tr = state.tracks
    tried: dict[int, int] = {}
    last = int(state.registered.sum())
    while True:
        live = state.active & state.has_point[tr.track] & ~state.registered[tr.frame]
        counts = np.bincount(tr.frame[live], minlength=len(state.registered))
        todo = [int(f) for f in np.flatnonzero(~state.registered)
                if counts[f] >= 3 and counts[f] > 1.25 * tried.get(int(f), 0)]
        if not todo:
            for f in np.flatnonzero(~state.registered):
                state.reasons.setdefault(int(f), f"only {counts[f]} matches to reconstructed points")
            break
        frame = int(max(todo, key=lambda f: counts[f]))
        tried[frame] = int(counts[frame])
        why = _register(state, frame, camera, options)
        if why:
            why = _register_relative(state, frame, options) and why  # the PnP reason when both fail
        if why:
            state.reasons[frame] = why
            continue
        state.reasons.pop(frame, None)
        seen = np.zeros(len(state.has_point), bool)
        seen[tr.track[tr.frame == frame]] = True
        _triangulate(state, camera, seen, options.outlier_threshold_px, options.min_angle_deg)
        if state.registered.sum() >= 1.25 * last:
            last = int(state.registered.sum())
            camera, stats = _adjust(state, camera, options, priors, self_calibrate=False)
            log.append(stats)
    return camera


def _complete(state: _State, camera: Camera, options: ReconstructionOptions) -> int:
    """Give rejected observations a second chance against the current model (they were judged with
    rougher cameras), then triangulate every track that can be and refine all points. Returns how many
    observations joined the model."""
    tr = state.tracks
    before = int((state.active & state.has_point[tr.track] & state.registered[tr.frame]).sum())
    state.active[~state.has_point[tr.track]] = True
    sel = np.flatnonzero(state.has_point[tr.track] & ~state.active & state.registered[tr.frame])
    R, C = _rotations(state)[tr.frame[sel]], state.centres[tr.frame[sel]]
    fits = _errors(camera, R, C, state.points[tr.track[sel]], state.xy[sel]) <= options.outlier_threshold_px
    state.active[sel[fits]] = True
    _triangulate(state, camera, np.ones(len(state.has_point), bool), options.outlier_threshold_px,
                 options.min_angle_deg)
    _refine_all_points(state, camera, options.outlier_threshold_px)
    return int((state.active & state.has_point[tr.track] & state.registered[tr.frame]).sum()) - before


def _new_state(tracks: Tracks, features: Sequence[np.ndarray], normalised: Sequence[np.ndarray]) -> _State:
    n = len(features)
    xy = np.array([features[f][k] for f, k in zip(tracks.frame, tracks.feature, strict=True)]).reshape(-1, 2)
    ideal = np.array([normalised[f][k] for f, k in zip(tracks.frame, tracks.feature, strict=True)]).reshape(-1, 2)
    return _State(tracks, xy.astype(np.float64), np.column_stack([ideal, np.ones(len(ideal))]),
                  np.zeros((n, 3)), np.zeros((n, 3)), np.zeros(n, bool), np.zeros((tracks.n_tracks, 3)),
                  np.zeros(tracks.n_tracks, bool), np.ones(len(tracks.track), bool))


def _check_inputs(features: Sequence[np.ndarray], matches: PairMatches, gps: Mapping | None,
                  attitude: Mapping | None, names: Sequence[str] | None) -> None:
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
def _result(state: _State, camera: Camera, priors: _Priors, names: list[str], info: dict) -> Reconstruction:
    tr = state.tracks
    out = np.flatnonzero(state.has_point)
    row = np.full(len(state.has_point), -1)
    row[out] = np.arange(len(out))
    sel = state.has_point[tr.track] & state.registered[tr.frame]
    frames = tr.frame[sel]
    cam = np.einsum("kij,kj->ki", _rotations(state)[frames], state.points[tr.track[sel]] - state.centres[frames])
    residuals = ObservationResiduals(frames, row[tr.track[sel]], state.xy[sel], camera.project(cam) - state.xy[sel],
                                     state.active[sel])
    poses = {int(f): (_rotations(state)[f], state.centres[f].copy()) for f in np.flatnonzero(state.registered)}
    triangulated = _gcps_triangulated(state, camera, priors)
    gcp_report, positions = report_gcps(priors.gcps, priors.gcp_obs, priors.checkpoints, state.registered,
                                        info["log"][-1]["gcp"], triangulated, state.world)
    inl = residuals.inlier
    report = {
        "frames": _frames_report(state, names),
        "world_frame": "local (E - E0, N - N0, height) metres" if state.world else
                       "arbitrary: scale set by the initial pair's baseline = 1",
        "initialisation": info["initialisation"], "datum": info["datum"],
        "points": len(out), "observations": int(inl.sum()), "rejected_observations": int((~inl).sum()),
        "rms_reprojection_px": _num(bundle.rms(residuals.residual[inl])),
        "per_frame": _per_frame(state, priors, names, residuals),
        "gcps": gcp_report,
        "checkpoint_rmse_m": checkpoint_rmse(gcp_report),
        "camera": camera.to_json(),
        "adjustments": [{k: v for k, v in s.items() if k != "gcp"} for s in info["log"]],
        "seconds": round(info["seconds"], 3), "notes": state.notes,
    }
    return Reconstruction(poses, state.points[out], out.astype(np.int64), camera, residuals, positions, report)


def _frames_report(state: _State, names: list[str]) -> dict:
    missing = {names[f]: state.reasons.get(int(f), "no verified matches to the registered frames")
               for f in np.flatnonzero(~state.registered)}
    return {"total": len(names), "registered": int(state.registered.sum()), "not_registered": missing}


def _per_frame(state: _State, priors: _Priors, names: list[str], residuals: ObservationResiduals) -> dict:
    by_frame = bundle.rms_by_group(residuals.residual[residuals.inlier], residuals.frame[residuals.inlier])
    out: dict[str, dict] = {}
    for f in np.flatnonzero(state.registered):
        rms_px, count = by_frame.get(int(f), (float("nan"), 0))
        entry: dict[str, Any] = {"rms_px": _num(rms_px), "observations": count}
        if state.world and int(f) in priors.gps:
            enu = state.centres[f] - np.asarray(priors.gps[int(f)].position)
            entry.update(gps_residual_m=_num(float(np.linalg.norm(enu))), gps_residual_enu_m=[_num(v) for v in enu])
        out[names[f]] = entry
    return out


def _empty(state: _State, camera: Camera, names: list[str], seeded: str, started: float) -> Reconstruction:
    for f in range(len(names)):
        state.reasons.setdefault(f, seeded)
    state.registered[:] = False
    z = np.zeros(0, np.int64)
    residuals = ObservationResiduals(z, z, np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0, bool))
    report = {"frames": _frames_report(state, names), "initialisation": seeded, "points": 0,
              "rms_reprojection_px": None, "seconds": round(time.perf_counter() - started, 3), "notes": state.notes}
    return Reconstruction({}, np.zeros((0, 3)), z, camera, residuals, {}, report)


def _num(value: float) -> float | None:
    """A JSON-safe float (None for NaN), rounded to 6 decimals."""
    value = float(value)
    return None if not np.isfinite(value) else round(value, 6)
