"""Stage ``match_strips`` (mode ``strip``): tie points of aerial strip frames, coarse to fine
(:mod:`workers.algorithms.strips`).

Each candidate pair is registered on a pyramid built from the frames' working copies (a 1/``strip_reduction``
copy: the frames are decoded once, by ``load_images``), with the spread criterion choosing the level; its
tie points are then found at native resolution in windows read from the source frames, and given to the
planar adjustment in working-copy pixels (as floats: they keep their native precision). A part per pair, so a
route's pairs spread over every worker (``workers.pipeline``'s parted stages).
"""

from __future__ import annotations

import math
from functools import partial
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from gpu_kernels.backend import resolve_device
from workers.algorithms.mosaic import candidate_pairs, local_metres
from workers.algorithms.strips import (
    FramePyramid,
    along_strip,
    build_pyramid,
    coarsest_level,
    distant_pairs,
    feasible_levels,
    fine_tie_points,
    register_coarse,
)
from workers.config import MosaicConfig
from workers.parallel import RecentCache, keep_freed_memory, thread_count
from workers.photo_io import WindowReader
from workers.records import Frame, PairRecord
from workers.workspace import JobWorkspace, ProgressFn, noop_progress

GREEN = 1  # the channel the strip method runs on (BGR index)


STAGE = "match_strips"
PART_UNIT = "pair"  # what a part is, in the progress
# by (job folder, frame): the pyramids and window readers of the frames this process's pairs share
_PYRAMIDS: RecentCache[FramePyramid] = RecentCache(32)
_READERS: RecentCache[WindowReader] = RecentCache(32)


def plan(ws: JobWorkspace, cfg: MosaicConfig) -> list[str]:
    """A part per candidate pair: flight order, plus GPS neighbours when every frame has a fix; with GPS, less the
    pairs on the strip's line too far apart to overlap, scaled by registering one neighbouring pair here
    (:func:`_along_strip`): at 55 % overlap, 25 of a 16-frame strip's 54 candidates, each of which took the coarse
    registration's every attempt (1.7 s) to fail. The others' predicted overlap goes to their parts, which start
    coarse to fine at the first level it can hold a match on (``feasible_levels``)."""
    frames = ws.load_frames()
    with_gps = all(f.gps for f in frames)
    positions = local_metres(np.array([[f.gps["lat"], f.gps["lon"]] for f in frames if f.gps])) if with_gps else None
    pairs = candidate_pairs(len(frames), positions, cfg.max_pair_gap, cfg.gps_neighbours, cfg.exhaustive_max_frames)
    placed: dict[tuple[int, int], tuple[float, float, float]] = {}
    reference: dict[str, Any] = {}
    if positions is not None:
        placed, reference = _along_strip(ws, cfg, frames, positions, pairs)
    distant = set(distant_pairs(placed, DISTANT_MARGIN))
    key = {pair: f"{frames[pair[0]].index:05d}_{frames[pair[1]].index:05d}" for pair in pairs}
    ws.save_part_inputs(
        STAGE,
        {
            "distant_pairs": [[frames[a].name, frames[b].name] for a, b in pairs if (a, b) in distant],
            "reference": reference,
            # native px across the thinner side of each kept pair's predicted overlap (on the strip's line)
            "overlap_px": {key[pair]: round(thin, 1) for pair, (_, _, thin) in placed.items() if pair not in distant},
        },
    )
    return [key[pair] for pair in pairs if pair not in distant]


DISTANT_MARGIN = 1.25  # left out past this many times the shift at which two frames stop meeting (GPS, attitude)


def _along_strip(
    ws: JobWorkspace, cfg: MosaicConfig, frames: list[Frame], positions: np.ndarray, pairs: list[tuple[int, int]]
) -> tuple[dict[tuple[int, int], tuple[float, float, float]], dict[str, Any]]:
    """Where GPS puts the candidate ``pairs`` (indices into ``frames``) on the strip (``along_strip``: shift,
    the shift at which frames stop meeting, the overlap's thinner side, px), scaled by the first of the neighbouring
    pairs nearest the strip's middle that registers with the spread criterion met; none when none does. Also what
    the scale came from, for the report."""
    middle = len(frames) // 2
    neighbours = [(k, k + 1) for k in (middle, middle - 1, middle + 1) if 0 <= k < len(frames) - 1]
    folder = str(Path(ws.root).resolve())
    for a, b in neighbours:
        pyramid_a, pyramid_b = (
            _PYRAMIDS.get((folder, f.index), partial(_pyramid, ws, f)) for f in (frames[a], frames[b])
        )
        coarse = register_coarse(
            pyramid_a, pyramid_b, min_spread=cfg.strip_min_spread, device=resolve_device(cfg.device)
        )
        if coarse.homography is not None and coarse.satisfied:
            size = (frames[a].orig_width, frames[a].orig_height)
            placed = along_strip(pairs, positions, size, (a, b), coarse.homography)
            return placed, {"pair": [frames[a].name, frames[b].name], "margin": DISTANT_MARGIN}
    return {}, {}


def part_threads(cfg: MosaicConfig) -> int:
    """A thread per core on the CPU; on a GPU one pair at a time unless ``threads`` asks for more. On an H200 a
    pair took 0.43 s, most of it decoding native windows on one core (Harris on a whole 75000 x 1800 frame: 19
    ms): threads would overlap that decoding, but CuPy from several threads has not run on a GPU here yet."""
    if resolve_device(cfg.device) == "cuda":
        return max(1, cfg.threads)
    return thread_count(cfg.threads)


def run_part(ws: JobWorkspace, cfg: MosaicConfig, key: str) -> dict[str, Any]:
    """Tie points of pair ``key``: ``matches/pair_I_J.npz`` when it is accepted; the record is its
    ``PairRecord`` and what the coarse registration chose."""
    keep_freed_memory()  # native windows of aerial frames, made and dropped pair after pair (workers.parallel)
    i, j = (int(k) for k in key.split("_"))
    by_index = {f.index: f for f in ws.load_frames()}
    fa, fb = by_index[i], by_index[j]
    device = resolve_device(cfg.device)
    folder = str(Path(ws.root).resolve())
    pyramid_a, pyramid_b = (_PYRAMIDS.get((folder, f.index), partial(_pyramid, ws, f)) for f in (fa, fb))
    levels = sorted(set(pyramid_a.levels) & set(pyramid_b.levels), reverse=True)
    thin = ws.load_part_inputs(STAGE).get("overlap_px", {}).get(key)
    if thin is not None:  # GPS's prediction: no attempt on levels too coarse to hold a match across the overlap
        levels = feasible_levels(levels, float(thin))
    coarse = register_coarse(pyramid_a, pyramid_b, min_spread=cfg.strip_min_spread, levels=levels, device=device)
    detail: dict[str, Any] = {"level": coarse.level, "spread": round(coarse.spread, 3), "note": coarse.reason}
    if coarse.homography is None:
        return {"pair": PairRecord(i, j, 0, 0, False, "H", None).to_json(), "detail": detail}
    reader_a, reader_b = (_READERS.get(f.path, partial(WindowReader, f.path)) for f in (fa, fb))
    ties = fine_tie_points(
        reader_a, reader_b, coarse.homography, n_points=cfg.strip_tie_points, frames=(i, j), device=device
    )
    n = len(ties.points_a)
    detail["tie_points"] = n
    H = _to_working(fb) @ coarse.homography @ np.linalg.inv(_to_working(fa))
    peaks = int(ties.counts.get("peaks", n))
    if n < cfg.min_inliers:
        return {"pair": PairRecord(i, j, peaks, n, False, "H", H / H[2, 2]).to_json(), "detail": detail}
    ws.save_matches((i, j), _working_points(fa, ties.points_a), _working_points(fb, ties.points_b))
    record = PairRecord(i, j, peaks, n, True, "H", H / H[2, 2], tie_points=n)
    return {"pair": record.to_json(), "detail": detail}


def finish(
    ws: JobWorkspace, cfg: MosaicConfig, records: dict[str, dict[str, Any]], *, progress: ProgressFn = noop_progress
) -> dict[str, Any]:
    """Write ``pairs.json``: every pair tried, in the plan's order."""
    results = [PairRecord.from_json(r["pair"]) for r in records.values()]
    ws.save_pairs(results)
    frames = ws.load_frames()
    names = {f.index: f.name for f in frames}
    details = {
        f"{names[r.pair[0]]}|{names[r.pair[1]]}": rec["detail"]
        for r, rec in zip(results, records.values(), strict=True)
    }
    inputs = ws.load_part_inputs(STAGE)
    return {
        "pairs_tried": len(results),
        "pairs_accepted": sum(r.accepted for r in results),
        # candidates left out: on the strip's line, GPS put them too far apart to overlap (scaled by "reference")
        "pairs_distant": inputs.get("distant_pairs", []),
        "distant_reference": inputs.get("reference", {}),
        "selection": "gps+order" if all(f.gps for f in frames) else "order",
        "device": resolve_device(cfg.device),
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
