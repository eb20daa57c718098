"""Stage ``detect_features``: SIFT keypoints and descriptors of every frame, found on a registration copy
(``registration_max_px``) and given in working-copy pixels, so later stages never see the smaller copy."""

from __future__ import annotations

from typing import Any

import cv2

from gpu_kernels.backend import resolve_device
from workers.algorithms.mosaic import detect, detector_name, registration_copy, tie_corners, to_full_pixels
from workers.config import MosaicConfig
from workers.parallel import ordered_map, thread_count
from workers.records import Frame
from workers.workspace import JobWorkspace, ProgressFn, noop_progress


def run(ws: JobWorkspace, cfg: MosaicConfig, *, progress: ProgressFn = noop_progress) -> dict[str, Any]:
    """Write ``features/frame_NNNN.npz`` (points, descriptors) for every frame of ``frames.json``."""
    frames = ws.load_frames()
    device = resolve_device(cfg.device)

    def one(frame: Frame) -> int:
        gray = cv2.cvtColor(ws.load_working_image(frame.index), cv2.COLOR_BGR2GRAY)
        # ortho: the bundle adjustment triangulates relief and needs tie points at working precision, which
        # the homography-guided refinement of planar mode cannot give it
        small, factors = (
            registration_copy(gray, cfg.registration_max_px) if cfg.mode == "planar" else (gray, (1.0, 1.0))
        )
        points, descriptors = detect(small, cfg.feature_type, device, cfg.max_features, cfg.ncc_half_window)
        ws.save_features(frame.index, to_full_pixels(points, factors), descriptors)
        if cfg.mode == "planar" and cfg.guided_matching:
            # where match_features correlates tie points: corners of the registration copy are as good a
            # place as the working copy's (the correlation, not the corner, gives the position), at 1/4 the cost
            ws.save_tie_corners(frame.index, to_full_pixels(tie_corners(small), factors))
        return len(points)

    # SIFT one frame at a time: OpenCV's already uses every core (measured: 2 threads gave no gain on 2 cores
    # and doubled peak memory), and a GPU is one shared device; ORB and the corners run on one core each
    threads = thread_count(cfg.threads) if cfg.feature_type == "orb" else 1
    counts = dict(zip([f.name for f in frames], ordered_map(one, frames, threads, progress, "frame"), strict=True))
    return {"device": device, "detector": detector_name(cfg.feature_type, device), "keypoints": counts}
