"""Stage ``load_images``: decode every input frame once and keep a downscaled working copy."""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np

from workers.config import MosaicConfig
from workers.parallel import ordered_map, thread_count
from workers.pipeline import PipelineError
from workers.records import Frame, RejectedFrame
from workers.workspace import JobWorkspace, ProgressFn, noop_progress

# what an input carries besides its pixels: EXIF's, or a GPS side file's (the api puts it in inputs.json)
EXIF_FIELDS = (
    "gps",
    "focal_length_mm",
    "focal_length_35mm",
    "yaw",
    "pitch",
    "roll",
    "relative_altitude",
    "gps_accuracy_m",
)


def run(ws: JobWorkspace, cfg: MosaicConfig, *, progress: ProgressFn = noop_progress) -> dict[str, Any]:
    """Read ``inputs.json``; write ``work/frame_NNNN.npy`` and ``frames.json``."""
    inputs = ws.load_inputs()

    def one(k: int) -> Frame | RejectedFrame:
        item = inputs[k]
        image = cv2.imread(item["path"], cv2.IMREAD_COLOR)
        if image is None:
            return RejectedFrame(k, item["name"], "could not be decoded")
        working, scale = _downscale(image, cfg.working_max_px)
        ws.save_working_image(k, working)
        metadata = {name: item.get(name) for name in EXIF_FIELDS}
        height, width = image.shape[:2]
        del image  # the full decode is the largest array of the stage: one per thread at a time
        return Frame(
            k, item["name"], item["path"], width, height, working.shape[1], working.shape[0], scale, **metadata
        )

    # A thread per core: libjpeg and cv2.resize release the GIL, and each frame is its own file.
    done = ordered_map(one, list(range(len(inputs))), thread_count(cfg.threads), progress, "frame")
    frames = [f for f in done if isinstance(f, Frame)]
    rejected = [f for f in done if isinstance(f, RejectedFrame)]
    if len(frames) < 2:
        raise PipelineError(f"only {len(frames)} of {len(inputs)} frames could be decoded; a mosaic needs 2")
    ws.save_frames(frames, rejected)
    progress(1.0, f"frame {len(inputs)}/{len(inputs)}")
    return {"frames": len(frames), "rejected": len(rejected)}


def _downscale(image: np.ndarray, max_px: int) -> tuple[np.ndarray, float]:
    """The image shrunk (INTER_AREA, no aliasing) so its longest side is at most ``max_px``."""
    longest = max(image.shape[:2])
    if longest <= max_px:
        return np.ascontiguousarray(image), 1.0
    scale = max_px / longest
    size = (max(1, round(image.shape[1] * scale)), max(1, round(image.shape[0] * scale)))
    return cv2.resize(image, size, interpolation=cv2.INTER_AREA), scale
