"""Stage ``match_features``: ratio-test matches and a USAC model for each candidate pair.

The model is a homography in planar mode (the frames are chained by it) and a fundamental matrix in
ortho mode (the scene may have relief; the bundle adjustment triangulates it). In planar mode, features
found on reduced registration copies give tie points only as fine as those copies, so the kept tie points
are refined on the working copies by NCC through the pair's homography.

Each frame's FLANN index is built once and shared by its pairs; in planar mode the first matches of a pair
predict its overlap, and only the features there are searched (see ``match_ratio``).
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any, Literal

import cv2
import numpy as np

from gpu_kernels.backend import Device, resolve_device
from workers.algorithms.mosaic import (
    OverlapGuide,
    PairIndices,
    candidate_pairs,
    chain_homographies,
    estimate_fundamental,
    estimate_homography,
    guided_tie_points,
    local_metres,
    match,
    overlap_share,
    refine_tie_points,
    refit_homography,
    spanning_tree,
    spread_subset,
    tie_corners,
)
from workers.config import MosaicConfig
from workers.parallel import ordered_map, thread_count
from workers.records import Frame, PairRecord
from workers.workspace import JobWorkspace, ProgressFn, noop_progress


def run(ws: JobWorkspace, cfg: MosaicConfig, *, progress: ProgressFn = noop_progress) -> dict[str, Any]:
    """Write ``matches/pair_I_J.npz`` (inlier tie points) and ``pairs.json`` (every pair tried)."""
    frames = ws.load_frames()
    with_gps = all(f.gps for f in frames)
    positions = local_metres(np.array([[f.gps["lat"], f.gps["lon"]] for f in frames if f.gps])) if with_gps else None
    pairs = candidate_pairs(len(frames), positions, cfg.max_pair_gap, cfg.gps_neighbours, cfg.exhaustive_max_frames)
    features = {f.index: ws.load_features(f.index) for f in frames}
    device = resolve_device(cfg.device)
    threads = 1 if device == "cuda" else thread_count(cfg.threads)
    # each frame's search index once, shared by its pairs in both directions (it was built per pair, twice)
    indices = PairIndices({k: desc for k, (_, desc) in features.items()}, pairs, cfg.feature_type, device)
    results = ordered_map(
        lambda ab: _match_pair(ws, cfg, device, frames[ab[0]], frames[ab[1]], features, indices),
        pairs,
        threads,
        progress,
        "pair",
    )
    if _guided(cfg):
        progress(0.9, "guided matching")
        results = _guided_pass(ws, cfg, frames, results)
    ws.save_pairs(results)
    accepted = [r for r in results if r.accepted]
    exhaustive = not with_gps and len(frames) <= cfg.exhaustive_max_frames
    return {
        "pairs_tried": len(results),
        "pairs_accepted": len(accepted),
        "selection": "gps+order" if with_gps else ("exhaustive" if exhaustive else "order"),
        "pairs_guided": sum(r.found_by == "guided" for r in accepted),
    }


def _match_pair(
    ws: JobWorkspace,
    cfg: MosaicConfig,
    device: Device,
    fa: Frame,
    fb: Frame,
    features: dict[int, tuple[np.ndarray, np.ndarray]],
    indices: PairIndices,
) -> PairRecord:
    i, j = fa.index, fb.index
    (pts_i, desc_i), (pts_j, desc_j) = features[i], features[j]
    thresholds = (cfg.ratio_test, cfg.ncc_threshold, cfg.min_inliers)
    # planar: search only the overlap the first matches predict (the frames' other features have no partner)
    sizes = {"size_b": (fb.width, fb.height), "size_a": (fa.width, fa.height)}
    guide = OverlapGuide(pts_i, pts_j, threshold_px=cfg.ransac_threshold_px, **sizes) if cfg.mode == "planar" else None
    matches = match(desc_i, desc_j, cfg.feature_type, device, *thresholds, (indices.get(i), indices.get(j)), guide)
    indices.release((i, j))
    estimate = estimate_fundamental if cfg.mode == "ortho" else estimate_homography
    H, inliers = estimate(pts_i[matches[:, 0]], pts_j[matches[:, 1]], cfg.ransac_threshold_px)
    n_in = int(inliers.sum())
    accepted = H is not None and n_in >= cfg.min_inliers and n_in >= cfg.min_inlier_ratio * max(len(matches), 1)
    kind: Literal["H", "F"] = "H" if cfg.mode == "planar" else "F"
    if not accepted:
        return PairRecord(i, j, len(matches), n_in, False, kind, H)
    good = matches[inliers]
    keep = spread_subset(pts_i[good[:, 0]], (fa.width, fa.height), cfg.max_tie_points_per_pair)
    ties_i, ties_j = pts_i[good[keep, 0]].astype(np.float64), pts_j[good[keep, 1]].astype(np.float64)
    # tie points found on reduced copies, or ORB's (FAST corners on its pyramid's levels, about a level's pixel
    # apart), are only as fine as that: refined on the working copies, unless the guided pass measures the
    # pair's tie points afresh (it refines these only where it cannot)
    coarse = cfg.feature_type == "orb" or cfg.registration_max_px < max(fa.width, fa.height, fb.width, fb.height)
    if kind == "H" and H is not None and coarse and not _guided(cfg):
        ties_i, ties_j, close = _refined(ws, cfg, (i, j), ties_i, ties_j, H)
        ties_i, ties_j, keep = ties_i[close], ties_j[close], keep[close]
    ws.save_matches((i, j), ties_i, ties_j, good[keep, 0], good[keep, 1])
    return PairRecord(i, j, len(matches), n_in, True, kind, H, tie_points=len(keep))


def _guided(cfg: MosaicConfig) -> bool:
    return cfg.mode == "planar" and cfg.guided_matching


def _refined(
    ws: JobWorkspace, cfg: MosaicConfig, pair: tuple[int, int], ties_i: np.ndarray, ties_j: np.ndarray, H: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A pair's (N, 2) tie points refined on the working copies by NCC through its homography ``H``, and the
    (N,) bool of those to keep: within the inlier threshold of the model re-fitted on the refined points (USAC
    judged the coarser positions; the record keeps USAC's model, which align_frames compares its adjustment
    with), and refined, where enough are (the rest are that coarse)."""
    gray_i, gray_j = (cv2.cvtColor(ws.load_working_image(k, mmap=True), cv2.COLOR_BGR2GRAY) for k in pair)
    ties_i, ties_j, refined = refine_tie_points(gray_i, gray_j, ties_i, ties_j, H)
    _, close = refit_homography(ties_i, ties_j, H, cfg.ransac_threshold_px)
    if (close & refined).sum() >= cfg.min_inliers:
        close &= refined
    return ties_i, ties_j, close


GUIDED_SEARCH_PX = 12  # guided matching: largest error of a chained prediction searched, working px
GUIDED_REFINE_PX = 4  # the same about a pair's own model


def _guided_pass(
    ws: JobWorkspace, cfg: MosaicConfig, frames: list[Frame], results: list[PairRecord]
) -> list[PairRecord]:
    """Guided matching (:func:`guided_tie_points`): every pair's tie points correlated at corners spread over
    its overlap (area-based matching, as the source work does for strips); descriptor matches only say which
    frames overlap and how.

    - Accepted pairs: about their own homography. Features cluster where the texture suits the detector, and
      tie points from one part of an overlap let the block bend (synthetic GPS strip, ORB features refined on
      the working copies: frame corners 1.7 GSD off the truth; 0.23 GSD with guided tie points, 0.47 with SIFT's).
      Where too few correlate, the pair keeps its descriptor matches, refined.
    - Pairs that descriptor matching did not accept but that the accepted ones, chained through their spanning
      tree, say overlap by ``guided_min_overlap`` or more: about that prediction. These are the cross-links
      between flight lines, which binary features miss most.
    A pair takes the guided tie points when their homography has ``min_inliers`` inliers."""
    accepted = [r for r in results if r.accepted and r.model is not None]
    root, parent = spanning_tree(len(frames), {r.pair: float(r.inliers) for r in accepted})
    chained = chain_homographies(root, parent, {r.pair: r.model for r in accepted if r.model is not None})
    size = {f.index: (f.width, f.height) for f in frames}
    todo: list[tuple[int, np.ndarray, int]] = []
    for k, r in enumerate(results):
        if r.accepted and r.model is not None:
            todo.append((k, r.model, GUIDED_REFINE_PX))
        elif not r.accepted and r.i in chained and r.j in chained:
            H_ij = np.linalg.inv(chained[r.j]) @ chained[r.i]
            if overlap_share(H_ij, size[r.i], size[r.j]) >= cfg.guided_min_overlap:
                todo.append((k, H_ij / H_ij[2, 2], GUIDED_SEARCH_PX))

    def one(item: tuple[int, np.ndarray, int]) -> PairRecord:
        k, H_ij, search_px = item
        r = results[k]
        gray_i, gray_j = (cv2.cvtColor(ws.load_working_image(f, mmap=True), cv2.COLOR_BGR2GRAY) for f in r.pair)
        corners = ws.load_tie_corners(r.i) if ws.tie_corners_exist(r.i) else tie_corners(gray_i)
        pts_i, pts_j = guided_tie_points(
            gray_i, gray_j, corners, H_ij, cfg.max_tie_points_per_pair, search_px, fine_px=GUIDED_REFINE_PX
        )
        H, inliers = estimate_homography(pts_i, pts_j, cfg.ransac_threshold_px)
        if H is None or inliers.sum() < cfg.min_inliers:
            return _refine_features(ws, cfg, r) if r.accepted else r
        n_in = int(inliers.sum())
        ws.save_matches(r.pair, pts_i[inliers], pts_j[inliers])
        matches = r.matches if r.accepted else len(pts_i)
        return PairRecord(r.i, r.j, matches, max(n_in, r.inliers), True, "H", H, tie_points=n_in, found_by="guided")

    out = list(results)
    for (k, *_), record in zip(
        todo, ordered_map(one, todo, thread_count(cfg.threads), noop_progress, "pair"), strict=True
    ):
        out[k] = record
    return out


def _refine_features(ws: JobWorkspace, cfg: MosaicConfig, r: PairRecord) -> PairRecord:
    """An accepted pair whose guided matching failed: its descriptor matches, refined (:func:`_refined`)."""
    ties_i, ties_j = ws.load_matches(r.pair)
    index_i, index_j = ws.load_match_indices(r.pair)
    assert r.model is not None  # an accepted planar pair has its homography
    ties_i, ties_j, close = _refined(ws, cfg, r.pair, ties_i, ties_j, r.model)
    ws.save_matches(r.pair, ties_i[close], ties_j[close], index_i[close], index_j[close])
    return replace(r, tie_points=int(close.sum()))
