"""Bundle adjustment of a growing reconstruction (:mod:`workers.algorithms.sfm.incremental`) with its world
terms (GPS priors on camera centres, GCP controls and tie points), and moving it onto the GPS / GCP datum.
Used by :func:`workers.algorithms.sfm.reconstruction.reconstruct`."""

from __future__ import annotations

import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np

from workers.algorithms.geometry import Camera, vector_from_rotation
from workers.algorithms.mosaic import spread_subset
from workers.algorithms.sfm import bundle
from workers.algorithms.sfm.datum import (
    DATUM_FIT,
    DATUM_LINE,
    DATUM_NONE,
    GpsFix,
    control_layout,
    line_similarity,
    refine_similarity,
    similarity_3d,
    triangulate_gcps,
)
from workers.algorithms.sfm.gcp import GroundControlPoint
from workers.algorithms.sfm.incremental import ReconstructionState, reprojection_errors, state_rotations

if TYPE_CHECKING:  # the options type only; reconstruction imports this module
    from workers.algorithms.sfm.reconstruction import ReconstructionOptions


@dataclass(frozen=True)
class Priors:
    """World-frame measurements: GPS fixes and GCPs, already mapped to frame indices."""

    gps: Mapping[int, GpsFix]
    gcps: Sequence[GroundControlPoint]
    gcp_obs: list[tuple[int, int, np.ndarray]]  # (gcp index, frame, (2,) px)
    checkpoints: frozenset[str]
    focal: float  # the initial focal length, px


def _ba_points(state: ReconstructionState, camera: Camera, per_frame: int) -> np.ndarray:
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


def adjust_state(
    state: ReconstructionState, camera: Camera, options: ReconstructionOptions, priors: Priors, self_calibrate: bool
) -> tuple[Camera, dict]:
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
    problem = bundle.BundleProblem(
        camera,
        state.rvecs[frames],
        state.centres[frames],
        state.points[ids],
        row_of[tr.frame[obs]],
        point_row[tr.track[obs]],
        state.xy[obs],
    )
    problem, gcp_ids = _with_world_terms(problem, state, row_of, priors, options, camera)
    problem = replace(problem, focal_prior=(priors.focal, options.focal_sigma * priors.focal))
    flags = dict(refine_focal=options.refine_focal, refine_k1=options.refine_k1, refine_k2=options.refine_k2)
    bopts = bundle.BundleOptions(
        options.loss,
        options.loss_scale_px,
        options.outlier_threshold_px,
        max_nfev=options.max_nfev,
        **(flags if self_calibrate else {}),
    )
    started = time.perf_counter()
    result = bundle.adjust(problem, bopts)
    state.rvecs[frames], state.centres[frames] = result.rvecs, result.centres
    state.points[ids] = result.points[: len(ids)]
    state.active[obs[~result.inlier[: len(obs)]]] = False
    refine_all_points(state, result.camera, options.outlier_threshold_px)
    stats = {
        "frames": len(frames),
        "points": len(ids),
        "observations": len(obs),
        "nfev": result.nfev,
        "seconds": round(time.perf_counter() - started, 3),
        "gcp": {
            gid: (
                result.points[len(ids) + k],
                result.residuals[len(obs) :][problem.obs_point[len(obs) :] == len(ids) + k],
            )
            for k, gid in enumerate(gcp_ids)
        },
    }
    return result.camera, stats


def _with_world_terms(
    problem: bundle.BundleProblem,
    state: ReconstructionState,
    row_of: np.ndarray,
    priors: Priors,
    options: ReconstructionOptions,
    camera: Camera,
) -> tuple[bundle.BundleProblem, list[str]]:
    """Add GPS priors and GCP points / observations / priors, or the gauge of an arbitrary frame."""
    if not state.world:
        a, b = state.gauge if state.gauge else (int(np.flatnonzero(state.registered)[0]),) * 2
        return replace(
            problem, fixed_frames=np.array([row_of[a]]), gauge_pair=(int(row_of[a]), int(row_of[b])) if a != b else None
        ), []
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
    return replace(
        problem,
        points=np.vstack([problem.points, gcp_xyz]),
        obs_frame=np.r_[problem.obs_frame, np.asarray([r[0] for r in rows], dtype=np.int64)],
        obs_point=np.r_[problem.obs_point, np.asarray([r[1] for r in rows], dtype=np.int64)],
        obs_xy=np.vstack([problem.obs_xy, np.asarray(xy).reshape(-1, 2)]),
        gps_frame=row_of[np.asarray(gps, dtype=np.int64)],
        gps_xyz=gps_xyz,
        gps_sigma=sigma,
        prior_point=np.asarray(prior_rows, dtype=np.int64),
        prior_xyz=prior_xyz.reshape(-1, 3),
        prior_sigma=np.full(len(prior_rows), options.gcp_sigma_m),
        fixed_rotations=fixed_rot,
        protected=protected,
    ), gcp_ids


def _gcp_terms(state: ReconstructionState, camera: Camera, row_of: np.ndarray, priors: Priors, first_row: int) -> tuple:
    """GCPs in the adjustment: controls (known position, a prior) and tie points (two views or more)."""
    xyz: list[np.ndarray] = []
    ids: list[str] = []
    rows: list[tuple[int, int]] = []
    xy: list[np.ndarray] = []
    prior_rows: list[int] = []
    triangulated = gcps_triangulated(state, camera, priors)
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


def gcps_triangulated(state: ReconstructionState, camera: Camera, priors: Priors) -> dict[str, np.ndarray]:
    return triangulate_gcps(
        camera, state_rotations(state), state.centres, state.registered, priors.gcps, priors.gcp_obs
    )


def refine_all_points(state: ReconstructionState, camera: Camera, threshold_px: float) -> None:
    tr = state.tracks
    for _ in range(2):
        sel = np.flatnonzero(state.has_point[tr.track] & state.active & state.registered[tr.frame])
        R, C = state_rotations(state)[tr.frame[sel]], state.centres[tr.frame[sel]]
        state.points = bundle.refine_points(camera, R, C, state.xy[sel], tr.track[sel], state.points, iterations=3)
        err = reprojection_errors(camera, R, C, state.points[tr.track[sel]], state.xy[sel])
        state.active[sel[err > threshold_px]] = False
    live = state.active & state.registered[tr.frame]
    state.has_point &= np.bincount(tr.track[live], minlength=len(state.has_point)) >= 2


# -- datum ---------------------------------------------------------------------------------------------
def _apply_similarity(state: ReconstructionState, s: float, R: np.ndarray, t: np.ndarray) -> None:
    """Move the model: ``X' = s R X + t``; camera rotations become ``R_cam R^T``."""
    state.centres = s * state.centres @ R.T + t
    state.points = s * state.points @ R.T + t
    rot = state_rotations(state) @ R.T
    state.rvecs = np.array([vector_from_rotation(r) for r in rot])


def to_world(state: ReconstructionState, camera: Camera, priors: Priors, options: ReconstructionOptions) -> str:
    """Move an incremental model onto its control: a 3D similarity of camera centres and triangulated
    control points to the GPS fixes and known positions when these spread in 3D, else a line fit to the
    GPS fixes with level cameras (``datum.line_similarity``). Returns the method."""
    frames = [f for f in sorted(priors.gps) if state.registered[f]]
    known = {g.id: g.position for g in priors.gcps if g.position is not None and g.id not in priors.checkpoints}
    tri = {k: v for k, v in gcps_triangulated(state, camera, priors).items() if k in known}
    gps = np.array([priors.gps[f].position for f in frames], dtype=np.float64).reshape(-1, 3)
    src = np.vstack([state.centres[frames], np.array(list(tri.values())).reshape(-1, 3)])
    dst = np.vstack([gps, np.array([known[k] for k in tri]).reshape(-1, 3)])
    sigma = float(np.median([priors.gps[f].sigma_h for f in frames])) if frames else options.gcp_sigma_m
    layout = control_layout(dst, sigma)
    if layout == "spread":
        fit = similarity_3d(src, dst)
    elif layout == "line" and len(frames) >= 2:
        fit = line_similarity(state.centres[frames], gps, state_rotations(state)[frames])
    else:
        if not state.world:  # a model seeded on GPS + attitude is in the world frame already
            state.notes.append(
                "GPS fixes and control points too few or too close together for their accuracy: "
                "arbitrary frame, scale set by the initial baseline = 1"
            )
        return DATUM_NONE
    if tri:  # weigh GPS fixes and control points by their accuracy
        weights = np.r_[[priors.gps[f].sigma_h for f in frames], np.full(len(tri), options.gcp_sigma_m)]
        fit = refine_similarity(src, dst, weights, *fit)
    _apply_similarity(state, *fit)
    state.world = True
    return {"spread": DATUM_FIT, "line": DATUM_LINE}[layout]
