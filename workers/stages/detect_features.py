"""Stage ``detect_features``: keypoints and descriptors of every frame, found on a registration copy
(``registration_max_px``; ortho mode ``ortho_registration_max_px``) and given in working-copy pixels, so later
stages never see the smaller copy."""

from __future__ import annotations

from typing import Any

import cv2

from gpu_kernels.backend import resolve_device
from workers.algorithms.mosaic import detect, detector_name, registration_copy, tie_corners, to_full_pixels
from workers.config import MosaicConfig
from workers.parallel import thread_count
from workers.workspace import JobWorkspace, ProgressFn, noop_progress

PART_UNIT = "frame"  # what a part is, in the progress


def plan(ws: JobWorkspace, cfg: MosaicConfig) -> list[str]:
    """A part per frame of ``frames.json``."""
    return [f"{f.index:05d}" for f in ws.load_frames()]


def part_threads(cfg: MosaicConfig) -> int:
    """SIFT one frame at a time: OpenCV's already uses every core (measured: 2 threads gave no gain on 2 cores
    and doubled peak memory), and a GPU is one shared device; ORB and the corners run on one core each."""
    return thread_count(cfg.threads) if cfg.feature_type == "orb" else 1


def run_part(ws: JobWorkspace, cfg: MosaicConfig, key: str) -> dict[str, Any]:
    """Write ``features/frame_NNNN.npz`` (points, descriptors) of frame ``key`` and, in planar mode, its tie
    corners; the record is how many keypoints and on what they were found."""
    k = int(key)
    device = resolve_device(cfg.device)
    gray = cv2.cvtColor(ws.load_working_image(k), cv2.COLOR_BGR2GRAY)
    # ortho: the bundle adjustment triangulates relief and needs tie points at working precision (up to the default
    # working size), which the homography-guided refinement of planar mode cannot give it
    max_px = cfg.registration_max_px if cfg.mode == "planar" else cfg.ortho_registration_max_px
    small, factors = registration_copy(gray, max_px)
    points, descriptors = detect(small, cfg.feature_type, device, cfg.max_features, cfg.ncc_half_window)
    ws.save_features(k, to_full_pixels(points, factors), descriptors)
    if cfg.mode == "planar" and cfg.guided_matching:
        # where measure_ties correlates tie points: corners of the registration copy are as good a place as
        # the working copy's (the correlation, not the corner, gives the position), at 1/4 the cost
        ws.save_tie_corners(k, to_full_pixels(tie_corners(small), factors))
    return {"keypoints": len(points), "device": device}


def finish(
    ws: JobWorkspace, cfg: MosaicConfig, records: dict[str, dict[str, Any]], *, progress: ProgressFn = noop_progress
) -> dict[str, Any]:
    frames = ws.load_frames()
    devices = sorted({r["device"] for r in records.values()})
    return {
        "device": ",".join(devices),
        "detector": ",".join(detector_name(cfg.feature_type, d) for d in devices),
        "keypoints": {f.name: records[f"{f.index:05d}"]["keypoints"] for f in frames},
    }
