"""Feature tracks: chains of pairwise matches that follow one scene point through several frames.

Every (frame, feature) is a node and every match an edge; a track is a connected component (the
union-find of Moulon & Monasse, "Unordered feature tracking made fast and easy", CVMP 2012, computed
here with ``scipy.sparse.csgraph.connected_components``, which gives the same components in one
vectorised call). A component that holds two different features of one frame joins two scene points
through a wrong match somewhere; it is dropped whole, as OpenSfM and OpenMVG do, since there is no
way to tell which of its matches is wrong. Before that, ``verify_pairs`` keeps only the matches of a
pair that agree with one essential matrix, so that few wrong matches are left to join tracks; and
``initial_pair`` picks the pair a reconstruction starts from and ``relative_pose`` gives two-view poses.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from workers.algorithms.sfm.bundle import triangulate_rays

Pair = tuple[int, int]
PairMatches = Mapping[Pair, tuple[np.ndarray, np.ndarray]]


@dataclass(frozen=True)
class Tracks:
    """Track observations as three aligned ``(K,) int64`` arrays, sorted by track then frame.

    Attributes
    ----------
    track : track id, ``0 .. n_tracks - 1``, consecutive.
    frame : frame index of the observation.
    feature : feature index in that frame's feature list.
    """

    track: np.ndarray
    frame: np.ndarray
    feature: np.ndarray

    @property
    def n_tracks(self) -> int:
        return int(self.track.max()) + 1 if len(self.track) else 0

    def lengths(self) -> np.ndarray:
        """(n_tracks,) int64 number of frames seeing each track."""
        return np.bincount(self.track, minlength=self.n_tracks)

    def in_frame(self, frame: int) -> tuple[np.ndarray, np.ndarray]:
        """Track ids and feature indices ``(M,) int64`` of the tracks seen in ``frame``."""
        sel = self.frame == frame
        return self.track[sel], self.feature[sel]


def build_tracks(matches: PairMatches, min_length: int = 2) -> Tracks:
    """Tracks from pairwise feature matches.

    Parameters
    ----------
    matches : (i, j) -> (features_i, features_j), two ``(M,) int`` arrays of feature indices; row m
        of each is one match between frame i and frame j (i != j).
    min_length : drop tracks seen in fewer frames than this (>= 2).

    Returns
    -------
    Tracks; empty when there are no matches. Tracks that hold two different features of the same
    frame (inconsistent matches) are dropped.
    """
    if min_length < 2:
        raise ValueError("min_length must be at least 2 (a track is seen in two frames or more)")
    frames, features = _edge_endpoints(matches)
    if frames.shape[1] == 0:
        return _empty()
    keys = np.stack([frames.ravel(), features.ravel()], axis=1)
    nodes, node_of = np.unique(keys, axis=0, return_inverse=True)
    node_of = node_of.reshape(2, -1)
    n = len(nodes)
    graph = coo_matrix((np.ones(node_of.shape[1]), (node_of[0], node_of[1])), shape=(n, n))
    _, component = connected_components(graph, directed=False)
    return _consistent_tracks(component, nodes[:, 0], nodes[:, 1], min_length)


def _edge_endpoints(matches: PairMatches) -> tuple[np.ndarray, np.ndarray]:
    """(2, E) frame and feature indices of both ends of every match."""
    frames, features = [], []
    for (i, j), (fi, fj) in matches.items():
        fi, fj = np.asarray(fi, dtype=np.int64).ravel(), np.asarray(fj, dtype=np.int64).ravel()
        if i == j or len(fi) != len(fj):
            raise ValueError(f"pair {(i, j)}: needs two different frames and equal-length index arrays")
        if len(fi) and min(fi.min(), fj.min()) < 0:
            raise ValueError(f"pair {(i, j)}: negative feature index")
        frames.append(np.stack([np.full(len(fi), i), np.full(len(fj), j)]))
        features.append(np.stack([fi, fj]))
    if not frames:
        return np.zeros((2, 0), np.int64), np.zeros((2, 0), np.int64)
    return np.concatenate(frames, axis=1).astype(np.int64), np.concatenate(features, axis=1)


def _consistent_tracks(component: np.ndarray, frame: np.ndarray, feature: np.ndarray, min_length: int) -> Tracks:
    """Renumber components into tracks, dropping those with a frame twice or too few frames."""
    order = np.lexsort((frame, component))
    comp, frm, feat = component[order], frame[order], feature[order]
    # sorted by (component, frame): a repeated frame inside a component sits next to itself
    repeated = (comp[1:] == comp[:-1]) & (frm[1:] == frm[:-1])
    bad = np.zeros(component.max() + 1, bool)
    bad[comp[1:][repeated]] = True
    length = np.bincount(comp, minlength=len(bad))
    keep_comp = ~bad & (length >= min_length)
    keep = keep_comp[comp]
    if not keep.any():
        return _empty()
    new_id = np.cumsum(keep_comp) - 1
    return Tracks(new_id[comp[keep]].astype(np.int64), frm[keep].astype(np.int64), feat[keep].astype(np.int64))


def _empty() -> Tracks:
    z = np.zeros(0, np.int64)
    return Tracks(z, z.copy(), z.copy())


def verify_pairs(
    normalised: Sequence[np.ndarray], matches: PairMatches, focal_px: float, threshold_px: float, min_inliers: int
) -> tuple[dict, dict]:
    """Keep the matches of each pair that fit one essential matrix (``cv2.findEssentialMat``, USAC_ACCURATE).

    Parameters
    ----------
    normalised : per frame (N_i, 2) ideal normalised feature coordinates.
    matches : (i, j) -> (features of i, features of j).
    focal_px : converts ``threshold_px`` to normalised units.

    Returns
    -------
    verified : (i, j) -> inlier (features_i, features_j), pairs with at least ``min_inliers``.
    essential : (i, j) -> (3, 3) essential matrix, ``x_j^T E x_i = 0``.
    """
    verified, essential = {}, {}
    for (i, j), (fi, fj) in matches.items():
        fi, fj = np.asarray(fi, dtype=np.int64), np.asarray(fj, dtype=np.int64)
        if len(fi) < max(min_inliers, 6):
            continue
        cv2.setRNGSeed(len(fi))  # same matches, same model
        E, mask = cv2.findEssentialMat(
            normalised[i][fi],
            normalised[j][fj],
            np.eye(3),
            method=cv2.USAC_ACCURATE,
            prob=0.999,
            threshold=threshold_px / focal_px,
        )
        if E is None or mask is None or E.shape[0] < 3:
            continue
        keep = mask.ravel().astype(bool)
        if keep.sum() >= min_inliers:
            verified[(i, j)], essential[(i, j)] = (fi[keep], fj[keep]), E[:3]
    return verified, essential


def initial_pair(
    verified: dict,
    essential: dict,
    normalised: Sequence[np.ndarray],
    min_inliers: int,
    min_angle_deg: float,
    good_angle_deg: float,
) -> tuple[int, int, np.ndarray, np.ndarray] | None:
    """The pair to start a reconstruction from (``verify_pairs`` output; the 20 with most matches tried).

    Score: matches in front of both cameras (``cv2.recoverPose``), scaled down by ``median angle /
    good_angle_deg`` below that angle (a short baseline triangulates poorly); pairs under
    ``min_inliers`` or ``min_angle_deg`` are skipped.

    Returns
    -------
    (i, j, R, t) with ``X_j = R X_i + t``, ``|t| = 1``; None when no pair qualifies.
    """
    best, best_score = None, 0.0
    for i, j in sorted(verified, key=lambda p: -len(verified[p][0]))[:20]:
        x1, x2 = normalised[i][verified[(i, j)][0]], normalised[j][verified[(i, j)][1]]
        n, R, t, mask = cv2.recoverPose(essential[(i, j)], x1, x2, np.eye(3))
        good = mask.ravel() > 0
        if n < min_inliers:
            continue
        d1 = np.column_stack([x1[good], np.ones(good.sum())])
        d2 = np.column_stack([x2[good], np.ones(good.sum())]) @ R  # rows: R^T d
        cos = np.sum(d1 * d2, axis=1) / np.linalg.norm(d1, axis=1) / np.linalg.norm(d2, axis=1)
        angle = float(np.degrees(np.median(np.arccos(np.clip(cos, -1, 1)))))
        score = n * min(1.0, angle / good_angle_deg) if angle >= min_angle_deg else 0.0
        if score > best_score:
            best, best_score = (i, j, R, t.ravel()), score
    return best


def relative_pose(
    E: np.ndarray, x_i: np.ndarray, x_j: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Camera j relative to camera i from their essential matrix (``cv2.recoverPose``), and every match
    triangulated with a unit baseline (multi-view midpoint).

    Parameters
    ----------
    E : (3, 3) with ``x_j^T E x_i = 0``; x_i, x_j : (M, 2) ideal normalised matched points.

    Returns
    -------
    R (3, 3), t (3,) with ``X_j = R X_i + t`` and ``|t| = 1``; points (M, 3) in camera i's frame;
    ok (M,) bool: in front of both cameras and triangulated.
    """
    _, R, t, mask = cv2.recoverPose(E, x_i, x_j, np.eye(3))
    t = t.ravel()
    rays = np.vstack([np.column_stack([x_i, np.ones(len(x_i))]), np.column_stack([x_j, np.ones(len(x_j))]) @ R])
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    origin = np.vstack([np.zeros((len(x_i), 3)), np.tile(-R.T @ t, (len(x_i), 1))])
    points, solved = triangulate_rays(origin, rays, np.tile(np.arange(len(x_i)), 2), len(x_i))
    return R, t, points, solved & (mask.ravel() > 0)
