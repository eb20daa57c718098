"""The growing model of an incremental reconstruction and what grows it: triangulating tracks, and
registering a frame by PnP (RANSAC + Levenberg-Marquardt) or, failing that, by its relative pose to a
registered frame. Used by :func:`workers.algorithms.sfm.reconstruction.reconstruct`."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np

from workers.algorithms.geometry import Camera, rotations_from_vectors, vector_from_rotation
from workers.algorithms.sfm.bundle import refine_points, triangulate_rays
from workers.algorithms.sfm.tracks import Tracks, relative_pose


@dataclass
class ReconstructionState:
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
    attitude: dict[int, str] = field(default_factory=dict)  # frame -> convention its prior was read in, or why unused
    reinitialised: dict[int, str] = field(default_factory=dict)  # frame -> why it was placed again after adjusting


def state_rotations(state: ReconstructionState) -> np.ndarray:
    return rotations_from_vectors(state.rvecs)


def triangulate_tracks(
    state: ReconstructionState, camera: Camera, wanted: np.ndarray, max_error_px: float, min_angle_deg: float
) -> int:
    """Triangulate tracks ``wanted`` (T,) bool from their active observations in registered frames;
    observations beyond ``max_error_px`` are dropped and the track tried once more. Returns points made."""
    made = 0
    for _ in range(2):
        tr = state.tracks
        sel = wanted[tr.track] & ~state.has_point[tr.track] & state.active & state.registered[tr.frame]
        if not sel.any():
            break
        ids, group = np.unique(tr.track[sel], return_inverse=True)
        frames, R = tr.frame[sel], state_rotations(state)[tr.frame[sel]]
        C = state.centres[frames]
        d = np.einsum("kji,kj->ki", R, state.ray[sel])  # R^T ray: world direction
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        X, solved = triangulate_rays(C, d, group, len(ids))
        X = refine_points(camera, R, C, state.xy[sel], group, X, iterations=3)
        bad_obs = ~(reprojection_errors(camera, R, C, X[group], state.xy[sel]) <= max_error_px)
        ok = solved & (np.bincount(group, weights=bad_obs, minlength=len(ids)) == 0)
        ok &= max_ray_angle(d, group, len(ids)) >= np.radians(min_angle_deg)
        state.points[ids[ok]], state.has_point[ids[ok]] = X[ok], True
        made += int(ok.sum())
        state.active[np.flatnonzero(sel)[bad_obs & solved[group]]] = False  # then retry without them
    return made


def reprojection_errors(camera: Camera, R: np.ndarray, C: np.ndarray, X: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """(K,) reprojection error px of points X (K, 3) seen by cameras (R, C); inf behind a camera or unsolved."""
    cam = np.einsum("kij,kj->ki", R, np.nan_to_num(X, nan=0.0) - C)
    front = (cam[:, 2] > 1e-9) & np.all(np.isfinite(X), axis=1)
    err = np.full(len(cam), np.inf)
    err[front] = np.linalg.norm(camera.project(cam[front]) - xy[front], axis=1)
    return err


def max_ray_angle(d: np.ndarray, group: np.ndarray, n: int) -> np.ndarray:
    """Per group, the largest angle (rad) between a ray and the group's first ray (at least half
    the largest pairwise angle)."""
    first = np.full(n, -1)
    first[group[::-1]] = np.arange(len(group))[::-1]
    cos = np.clip(np.sum(d * d[first[group]], axis=1), -1.0, 1.0)
    angle = np.zeros(n)
    np.maximum.at(angle, group, np.arccos(cos))
    return angle


def register_by_pnp(
    state: ReconstructionState, frame: int, camera: Camera, min_inliers: int, threshold_px: float
) -> str | None:
    """Pose of ``frame`` by PnP RANSAC + Levenberg-Marquardt refinement; None on success, else why not."""
    tr = state.tracks
    sel = np.flatnonzero((tr.frame == frame) & state.has_point[tr.track] & state.active)
    if len(sel) < min_inliers:
        return f"only {len(sel)} matches to reconstructed points (needs {min_inliers})"
    K = camera.matrix()
    obj, img = state.points[tr.track[sel]], state.ray[sel, :2] * [camera.fx, camera.fy] + [camera.cx, camera.cy]
    cv2.setRNGSeed(len(sel))
    ok, rvec, tvec, inl = cv2.solvePnPRansac(
        obj,
        img,
        K,
        None,
        iterationsCount=1000,
        confidence=0.9999,
        reprojectionError=threshold_px,
        flags=cv2.SOLVEPNP_SQPNP,
    )
    n_in = 0 if inl is None else len(inl)
    if not ok or n_in < min_inliers:
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


def register_by_relative_pose(state: ReconstructionState, frame: int) -> str | None:
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
    Rr = state_rotations(state)[r]
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


def frame_observations(state: ReconstructionState) -> tuple[np.ndarray, np.ndarray]:
    """Per frame (F,) int64: the observations the model keeps (active, of a triangulated track; for a frame not
    registered, those it would keep) and the tie points its verified pairs offered (every track observation
    of the frame)."""
    tr = state.tracks
    n = len(state.registered)
    kept = np.bincount(tr.frame[state.active & state.has_point[tr.track]], minlength=n)
    return kept, np.bincount(tr.frame, minlength=n)


def unregister(state: ReconstructionState, frames: Sequence[int]) -> None:
    """Take ``frames`` out of the model, and the points that fewer than two registered frames still see; the
    frames' observations become active again, for when they are placed anew."""
    tr = state.tracks
    state.registered[list(frames)] = False
    state.active[np.isin(tr.frame, list(frames))] = True
    seen = state.active & state.registered[tr.frame] & state.has_point[tr.track]
    state.has_point &= np.bincount(tr.track[seen], minlength=len(state.has_point)) >= 2
    if state.gauge is not None and not state.registered[list(state.gauge)].all():
        # the frames that fix an arbitrary model's scale: the two registered ones with the most observations
        kept = np.bincount(tr.frame[seen], minlength=len(state.registered))
        best = [int(f) for f in np.argsort(-kept, kind="stable") if state.registered[f]][:2]
        state.gauge = (best[0], best[1]) if len(best) == 2 else None
