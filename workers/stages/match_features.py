"""Stage ``match_features``: ratio-test matches and a USAC model for each candidate pair, a part per pair.

The model is a homography in planar mode (the frames are chained by it) and a fundamental matrix in
ortho mode (the scene may have relief; the bundle adjustment triangulates it). In planar mode the next stage,
``measure_ties``, measures each pair's tie points afresh by correlation over its whole overlap; with
``guided_matching`` off, the matched features found on reduced registration copies (or ORB's, on its pyramid's
levels) are refined here on the working copies by NCC through the pair's homography.

Each process keeps the features and search index of the frames its pairs share (``RecentCache``); in planar
mode the first matches of a pair predict its overlap, and only the features there are searched (``match_ratio``).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Literal

import cv2
import numpy as np

from gpu_kernels.backend import Device, resolve_device
from workers.algorithms.mosaic import (
    OverlapGuide,
    SearchIndex,
    candidate_pairs,
    estimate_fundamental,
    estimate_homography,
    local_metres,
    match,
    match_index,
    refined_pair_ties,
    spread_subset,
)
from workers.config import MosaicConfig
from workers.parallel import RecentCache, thread_count
from workers.records import Frame, PairRecord
from workers.workspace import JobWorkspace, ProgressFn, noop_progress

FrameFeatures = tuple[np.ndarray, np.ndarray, SearchIndex | None]  # points, descriptors, search index
_FEATURES: RecentCache[FrameFeatures] = RecentCache(64)  # by (job folder, frame), for this process's pairs


PART_UNIT = "pair"  # what a part is, in the progress


def plan(ws: JobWorkspace, cfg: MosaicConfig) -> list[str]:
    """A part per candidate pair: flight order plus GPS neighbours when every frame has GPS, all pairs for up to
    ``exhaustive_max_frames`` frames without."""
    return [_key(a.index, b.index) for a, b in _candidates(ws.load_frames(), cfg)]


def part_threads(cfg: MosaicConfig) -> int:
    return 1 if resolve_device(cfg.device) == "cuda" else thread_count(cfg.threads)


def run_part(ws: JobWorkspace, cfg: MosaicConfig, key: str) -> dict[str, Any]:
    """Match pair ``key``; write ``matches/pair_I_J.npz`` when it is accepted; the record is its ``PairRecord``."""
    i, j = (int(k) for k in key.split("_"))
    frames = {f.index: f for f in ws.load_frames()}
    device = resolve_device(cfg.device)
    return {"pair": _match_pair(ws, cfg, device, frames[i], frames[j]).to_json()}


def finish(
    ws: JobWorkspace, cfg: MosaicConfig, records: dict[str, dict[str, Any]], *, progress: ProgressFn = noop_progress
) -> dict[str, Any]:
    """Write ``pairs.json``: every pair tried, in the plan's order."""
    results = [PairRecord.from_json(r["pair"]) for r in records.values()]
    ws.save_pairs(results)
    frames = ws.load_frames()
    with_gps = all(f.gps for f in frames)
    exhaustive = not with_gps and len(frames) <= cfg.exhaustive_max_frames
    return {
        "pairs_tried": len(results),
        "pairs_accepted": sum(r.accepted for r in results),
        "selection": "gps+order" if with_gps else ("exhaustive" if exhaustive else "order"),
    }


def _key(i: int, j: int) -> str:
    return f"{i:05d}_{j:05d}"


def _candidates(frames: list[Frame], cfg: MosaicConfig) -> list[tuple[Frame, Frame]]:
    with_gps = all(f.gps for f in frames)
    positions = local_metres(np.array([[f.gps["lat"], f.gps["lon"]] for f in frames if f.gps])) if with_gps else None
    pairs = candidate_pairs(len(frames), positions, cfg.max_pair_gap, cfg.gps_neighbours, cfg.exhaustive_max_frames)
    return [(frames[a], frames[b]) for a, b in pairs]


def _features(ws: JobWorkspace, cfg: MosaicConfig, device: Device, frame: int) -> FrameFeatures:
    def build() -> FrameFeatures:
        points, desc = ws.load_features(frame)
        return points, desc, match_index(desc, cfg.feature_type, device)

    return _FEATURES.get((str(Path(ws.root).resolve()), frame), build)


def _match_pair(ws: JobWorkspace, cfg: MosaicConfig, device: Device, fa: Frame, fb: Frame) -> PairRecord:
    i, j = fa.index, fb.index
    (pts_i, desc_i, index_i), (pts_j, desc_j, index_j) = (_features(ws, cfg, device, k) for k in (i, j))
    thresholds = (cfg.ratio_test, cfg.ncc_threshold, cfg.min_inliers)
    inlier_px = cfg.inlier_px(max(fa.width, fa.height, fb.width, fb.height))
    # planar: search only the overlap the first matches predict (the frames' other features have no partner)
    sizes = {"size_b": (fb.width, fb.height), "size_a": (fa.width, fa.height)}
    guide = OverlapGuide(pts_i, pts_j, threshold_px=inlier_px, **sizes) if cfg.mode == "planar" else None
    matches = match(desc_i, desc_j, cfg.feature_type, device, *thresholds, (index_i, index_j), guide)
    estimate = estimate_fundamental if cfg.mode == "ortho" else estimate_homography
    H, inliers = estimate(pts_i[matches[:, 0]], pts_j[matches[:, 1]], inlier_px)
    n_in = int(inliers.sum())
    accepted = H is not None and n_in >= cfg.min_inliers and n_in >= cfg.min_inlier_ratio * max(len(matches), 1)
    kind: Literal["H", "F"] = "H" if cfg.mode == "planar" else "F"
    if not accepted:
        return PairRecord(i, j, len(matches), n_in, False, kind, H)
    good = matches[inliers]
    keep = spread_subset(pts_i[good[:, 0]], (fa.width, fa.height), cfg.max_tie_points_per_pair)
    ties_i, ties_j = pts_i[good[keep, 0]].astype(np.float64), pts_j[good[keep, 1]].astype(np.float64)
    # tie points found on reduced copies, or ORB's (FAST corners on its pyramid's levels, about a level's pixel
    # apart), are only as fine as that: refined on the working copies, unless measure_ties measures the pair's
    # tie points afresh (it refines these only where it cannot)
    coarse = cfg.feature_type == "orb" or cfg.registration_max_px < max(fa.width, fa.height, fb.width, fb.height)
    if kind == "H" and H is not None and coarse and not (cfg.mode == "planar" and cfg.guided_matching):
        gray_i, gray_j = (cv2.cvtColor(ws.load_working_image(k, mmap=True), cv2.COLOR_BGR2GRAY) for k in (i, j))
        ties_i, ties_j, close = refined_pair_ties(gray_i, gray_j, ties_i, ties_j, H, inlier_px, cfg.min_inliers)
        ties_i, ties_j, keep = ties_i[close], ties_j[close], keep[close]
    ws.save_matches((i, j), ties_i, ties_j, good[keep, 0], good[keep, 1])
    return PairRecord(i, j, len(matches), n_in, True, kind, H, tie_points=len(keep))
