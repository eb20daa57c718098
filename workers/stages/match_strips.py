"""Stage ``match_strips`` (mode ``strip``): tie points of aerial strip frames, coarse to fine
(:mod:`workers.algorithms.strips`).

Each candidate pair is registered on a pyramid built from the frames' working copies (a 1/``strip_reduction``
copy: the frames are decoded once, by ``load_images``), with the spread criterion choosing the level; its
tie points are then found at native resolution in windows read from the source frames, and given to the
planar adjustment in working-copy pixels (as floats: they keep their native precision).
"""

from __future__ import annotations

import math
from typing import Any

import cv2
import numpy as np

from gpu_kernels.backend import resolve_device
from workers.algorithms.mosaic import candidate_pairs, local_metres
from workers.algorithms.strips import (
    FramePyramid,
    build_pyramid,
    coarsest_level,
    fine_tie_points,
    register_coarse,
)
from workers.config import MosaicConfig
from workers.parallel import ordered_map, thread_count
from workers.photo_io import WindowReader
from workers.records import Frame, PairRecord
from workers.workspace import JobWorkspace, ProgressFn, noop_progress

GREEN = 1  # the channel the strip method runs on (BGR index)


def run(ws: JobWorkspace, cfg: MosaicConfig, *, progress: ProgressFn = noop_progress) -> dict[str, Any]:
    """Write ``matches/pair_I_J.npz`` (tie points, working px) and ``pairs.json`` (every pair tried)."""
    frames = ws.load_frames()
    by_index = {f.index: f for f in frames}
    with_gps = all(f.gps for f in frames)
    positions = local_metres(np.array([[f.gps["lat"], f.gps["lon"]] for f in frames if f.gps])) if with_gps else None
    pairs = candidate_pairs(len(frames), positions, cfg.max_pair_gap, cfg.gps_neighbours, cfg.exhaustive_max_frames)
    device = resolve_device(cfg.device)
    threads = 1 if device == "cuda" else thread_count(cfg.threads)
    progress(0.0, "pyramids")
    pyramids = {f.index: _pyramid(ws, f) for f in frames}
    readers = {f.index: WindowReader(f.path) for f in frames}
    details: dict[str, dict[str, Any]] = {}

    def one(pair: tuple[int, int]) -> PairRecord:
        i, j = pair
        fa, fb = by_index[i], by_index[j]
        coarse = register_coarse(pyramids[i], pyramids[j], min_spread=cfg.strip_min_spread, device=device)
        key = f"{fa.name}|{fb.name}"
        details[key] = {"level": coarse.level, "spread": round(coarse.spread, 3), "note": coarse.reason}
        if coarse.homography is None:
            return PairRecord(i, j, 0, 0, False, "H", None)
        ties = fine_tie_points(
            readers[i], readers[j], coarse.homography, n_points=cfg.strip_tie_points, frames=pair, device=device
        )
        n = len(ties.points_a)
        details[key]["tie_points"] = n
        H = _to_working(fb) @ coarse.homography @ np.linalg.inv(_to_working(fa))
        if n < cfg.min_inliers:
            return PairRecord(i, j, int(ties.counts.get("peaks", n)), n, False, "H", H / H[2, 2])
        points_i = _working_points(fa, ties.points_a)
        points_j = _working_points(fb, ties.points_b)
        ws.save_matches(pair, points_i, points_j)
        return PairRecord(i, j, int(ties.counts.get("peaks", n)), n, True, "H", H / H[2, 2], tie_points=n)

    results = ordered_map(one, pairs, threads, progress, "pair")
    ws.save_pairs(results)
    return {
        "pairs_tried": len(results),
        "pairs_accepted": sum(r.accepted for r in results),
        "selection": "gps+order" if with_gps else "order",
        "device": device,
        "pairs": details,
    }


def _pyramid(ws: JobWorkspace, frame: Frame) -> FramePyramid:
    """The frame's pyramid from its working copy (green), labelled with the level nearest its reduction."""
    gray = np.ascontiguousarray(ws.load_working_image(frame.index)[..., GREEN])
    base = max(0, round(math.log2(frame.orig_width / frame.width)))
    top = coarsest_level((frame.orig_width, frame.orig_height))
    return build_pyramid(gray, (frame.orig_width, frame.orig_height), base, max(1, top - base + 1))


def _to_working(frame: Frame) -> np.ndarray:
    """(3, 3) native px -> working px, pixel centres at integers on both."""
    sx, sy = frame.width / frame.orig_width, frame.height / frame.orig_height
    return np.array([[sx, 0.0, 0.5 * sx - 0.5], [0.0, sy, 0.5 * sy - 0.5], [0.0, 0.0, 1.0]])


def _working_points(frame: Frame, native: np.ndarray) -> np.ndarray:
    pts = np.asarray(native, np.float64).reshape(-1, 1, 2)
    return cv2.perspectiveTransform(pts, _to_working(frame)).reshape(-1, 2)
