"""Stage ``match_features``: ratio-test matches and a USAC model for each candidate pair.

The model is a homography in planar mode (the frames are chained by it) and a fundamental matrix in
ortho mode (the scene may have relief; the bundle adjustment triangulates it). In planar mode, features
found on reduced registration copies give tie points only as fine as those copies, so the kept tie points
are refined on the working copies by NCC through the pair's homography.

Each frame's FLANN index is built once and shared by its pairs; in planar mode the first matches of a pair
predict its overlap, and only the features there are searched (see ``match_ratio``).
"""

from __future__ import annotations

from typing import Any, Literal

import cv2
import numpy as np

from gpu_kernels.backend import Device, resolve_device
from workers.algorithms.mosaic import (
    OverlapGuide,
    PairIndices,
    candidate_pairs,
    estimate_fundamental,
    estimate_homography,
    local_metres,
    match,
    refine_tie_points,
    refit_homography,
    spread_subset,
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
    ws.save_pairs(results)
    accepted = [r for r in results if r.accepted]
    exhaustive = not with_gps and len(frames) <= cfg.exhaustive_max_frames
    return {
        "pairs_tried": len(results),
        "pairs_accepted": len(accepted),
        "selection": "gps+order" if with_gps else ("exhaustive" if exhaustive else "order"),
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
    guide = OverlapGuide(pts_i, pts_j, (fb.width, fb.height), cfg.ransac_threshold_px) if cfg.mode == "planar" else None
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
    if kind == "H" and H is not None and cfg.registration_max_px < max(fa.width, fa.height, fb.width, fb.height):
        gray_i, gray_j = (cv2.cvtColor(ws.load_working_image(k, mmap=True), cv2.COLOR_BGR2GRAY) for k in (i, j))
        ties_i, ties_j, refined = refine_tie_points(gray_i, gray_j, ties_i, ties_j, H)
        # the inlier test again, at working precision, against the model re-fitted on the refined points
        # (USAC judged the coarser registration positions; the record keeps USAC's model, which align_frames
        # compares its adjustment with); only refined points where enough are (the rest are that coarse)
        _, close = refit_homography(ties_i, ties_j, H, cfg.ransac_threshold_px)
        if (close & refined).sum() >= cfg.min_inliers:
            close &= refined
        ties_i, ties_j, keep = ties_i[close], ties_j[close], keep[close]
    ws.save_matches((i, j), ties_i, ties_j, good[keep, 0], good[keep, 1])
    return PairRecord(i, j, len(matches), n_in, True, kind, H, tie_points=len(keep))
