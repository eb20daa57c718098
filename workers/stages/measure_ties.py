"""Stage ``measure_ties`` (planar mode): every pair's tie points measured by guided matching
(:func:`~workers.algorithms.mosaic.guided_tie_points`), a part per pair: corners spread over its whole overlap,
correlated about a homography, so that descriptor matches only say which frames overlap and how.

- Pairs ``match_features`` accepted: about their own homography. Features cluster where the texture suits the
  detector, and tie points from one part of an overlap let the block bend (synthetic GPS strip, ORB features
  refined on the working copies: frame corners 1.7 GSD off the truth; 0.23 GSD with guided tie points, 0.47
  with SIFT's). Where too few correlate, the pair keeps its descriptor matches, refined.
- Pairs it did not accept but that the accepted ones, chained through their spanning tree, say overlap by
  ``guided_min_overlap`` or more: about that prediction, searched within ``GUIDED_SEARCH_PX`` then 4 px. These
  are the cross-links between flight lines, which binary features miss most.
A pair correlates its share of ``tie_points_per_frame`` (:func:`tie_budgets`) and takes the guided tie points
when their homography has ``min_inliers`` inliers. With ``guided_matching`` off it has no parts.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import replace
from typing import Any

import cv2
import numpy as np

from workers.algorithms.mosaic import (
    chain_homographies,
    estimate_homography,
    guided_tie_points,
    overlap_share,
    refined_pair_ties,
    spanning_tree,
    tie_corners,
)
from workers.config import MosaicConfig
from workers.parallel import RecentCache
from workers.records import PairRecord
from workers.workspace import JobWorkspace, ProgressFn, noop_progress

GUIDED_SEARCH_PX = 12  # largest error of a chained prediction searched, working px
GUIDED_REFINE_PX = 4  # the same about a pair's own model
_INPUTS: RecentCache[dict[str, Any]] = RecentCache(4)  # the plan's inputs, read once per process and plan


PART_UNIT = "pair"  # what a part is, in the progress


def plan(ws: JobWorkspace, cfg: MosaicConfig) -> list[str]:
    """A part per pair to measure; the homography each is measured about is saved for the parts."""
    if not cfg.guided_matching:
        ws.save_part_inputs("measure_ties", {})
        return []
    frames = ws.load_frames()
    results = ws.load_pairs()
    accepted = [r for r in results if r.accepted and r.model is not None]
    root, parent = spanning_tree(len(frames), {r.pair: float(r.inliers) for r in accepted})
    chained = chain_homographies(root, parent, {r.pair: r.model for r in accepted if r.model is not None})
    size = {f.index: (f.width, f.height) for f in frames}
    about: dict[str, dict[str, Any]] = {}
    for r in results:
        if r.accepted and r.model is not None:
            about[_key(r)] = {"pair": r.to_json(), "H": r.model.tolist(), "search_px": GUIDED_REFINE_PX}
        elif not r.accepted and r.i in chained and r.j in chained:
            H_ij = np.linalg.inv(chained[r.j]) @ chained[r.i]
            if overlap_share(H_ij, size[r.i], size[r.j]) >= cfg.guided_min_overlap:
                about[_key(r)] = {"pair": r.to_json(), "H": (H_ij / H_ij[2, 2]).tolist(), "search_px": GUIDED_SEARCH_PX}
    measured = [r for r in results if _key(r) in about]
    budgets = tie_budgets([r.pair for r in measured], cfg)
    for r in measured:
        about[_key(r)]["max_points"] = budgets[r.pair]
    ws.save_part_inputs("measure_ties", about)
    return list(about)


def tie_budgets(pairs: list[tuple[int, int]], cfg: MosaicConfig) -> dict[tuple[int, int], int]:
    """How many corners each pair correlates: ``tie_points_per_frame`` shared among the pairs of the less busy of
    its two frames, at most ``max_tie_points_per_pair``. A frame's 8 parameters are fixed by all its pairs' tie
    points together: a 30-frame GPS flight (each frame in about 7 pairs) measured 200 a pair with the same
    0.12 px as 400, in 0.6 s instead of 1.0, and its adjustment took 0.4 s instead of 0.7; a short strip (2-3
    pairs a frame) keeps 400, which its weak second-neighbour pairs need to reach ``min_inliers``."""
    count = Counter(k for pair in pairs for k in pair)
    return {
        (i, j): min(cfg.max_tie_points_per_pair, -(-cfg.tie_points_per_frame // min(count[i], count[j])))
        for i, j in pairs
    }


def run_part(ws: JobWorkspace, cfg: MosaicConfig, key: str) -> dict[str, Any]:
    """Measure pair ``key``'s tie points; rewrite its ``matches/pair_I_J.npz``; the record is its new
    ``PairRecord``."""
    about = _INPUTS.get(
        (str(ws.root.resolve()), ws.part_inputs_version("measure_ties")), lambda: ws.load_part_inputs("measure_ties")
    )[key]
    r = PairRecord.from_json(about["pair"])
    i, j = r.pair
    H_ij = np.array(about["H"], np.float64)
    gray_i, gray_j = (cv2.cvtColor(ws.load_working_image(k, mmap=True), cv2.COLOR_BGR2GRAY) for k in (i, j))
    corners = ws.load_tie_corners(i) if ws.tie_corners_exist(i) else tie_corners(gray_i)
    budget = int(about.get("max_points", cfg.max_tie_points_per_pair))  # inputs an older plan saved have none
    pts_i, pts_j = guided_tie_points(
        gray_i, gray_j, corners, H_ij, budget, int(about["search_px"]), fine_px=GUIDED_REFINE_PX
    )
    H, inliers = estimate_homography(pts_i, pts_j, _inlier_px(cfg, gray_i, gray_j))
    if H is None or inliers.sum() < cfg.min_inliers:
        return {"pair": (_refine_features(ws, cfg, r, gray_i, gray_j) if r.accepted else r).to_json()}
    n_in = int(inliers.sum())
    ws.save_matches(r.pair, pts_i[inliers], pts_j[inliers])
    # the candidates examined: the descriptor matches, or the corners correlated when more (never fewer than inliers)
    matches = max(r.matches, len(pts_i)) if r.accepted else len(pts_i)
    guided = PairRecord(i, j, matches, max(n_in, r.inliers), True, "H", H, tie_points=n_in, found_by="guided")
    return {"pair": guided.to_json()}


def finish(
    ws: JobWorkspace, cfg: MosaicConfig, records: dict[str, dict[str, Any]], *, progress: ProgressFn = noop_progress
) -> dict[str, Any]:
    """Write ``pairs.json`` again with the pairs measured."""
    measured = {key: PairRecord.from_json(r["pair"]) for key, r in records.items()}
    before = ws.load_pairs()
    after = [measured.get(_key(r), r) for r in before]
    ws.save_pairs(after)
    return {
        "pairs_measured": len(measured),
        "pairs_guided": sum(r.found_by == "guided" for r in after if r.accepted),
        "pairs_found": sum(r.accepted and not b.accepted for r, b in zip(after, before, strict=True)),
    }


def _key(r: PairRecord) -> str:
    return f"{r.i:05d}_{r.j:05d}"


def _inlier_px(cfg: MosaicConfig, gray_i: np.ndarray, gray_j: np.ndarray) -> float:
    """The pair's homography inlier threshold on these working copies (``MosaicConfig.threshold_scale``)."""
    return cfg.inlier_px(max(*gray_i.shape[:2], *gray_j.shape[:2]))


def _refine_features(
    ws: JobWorkspace, cfg: MosaicConfig, r: PairRecord, gray_i: np.ndarray, gray_j: np.ndarray
) -> PairRecord:
    """An accepted pair whose guided matching failed: its descriptor matches, refined on the working copies."""
    ties_i, ties_j = ws.load_matches(r.pair)
    index_i, index_j = ws.load_match_indices(r.pair)
    assert r.model is not None  # an accepted planar pair has its homography
    inlier_px = _inlier_px(cfg, gray_i, gray_j)
    ties_i, ties_j, close = refined_pair_ties(gray_i, gray_j, ties_i, ties_j, r.model, inlier_px, cfg.min_inliers)
    ws.save_matches(r.pair, ties_i[close], ties_j[close], index_i[close], index_j[close])
    return replace(r, tie_points=int(close.sum()))
