"""Stage ``load_images``: decode every input frame once and keep a downscaled working copy."""

from __future__ import annotations

import math
from typing import Any

from workers.config import MosaicConfig
from workers.parallel import ordered_map, thread_count
from workers.photo_io import read_reduced
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
        # a JPEG is decoded whole (the largest array of the stage, one per thread at a time); a TIFF is
        # averaged down block by block, never decoded whole
        max_px = cfg.working_max_px
        if cfg.mode == "strip":  # a pyramid level of the frame: 1/strip_reduction of its longest side
            max_px = max(1, math.ceil(max(item["width"], item["height"]) / cfg.strip_reduction))
        found = read_reduced(item["path"], max_px)
        if found is None:
            return RejectedFrame(k, item["name"], "could not be decoded")
        working, (width, height) = found
        ws.save_working_image(k, working)
        metadata = {name: item.get(name) for name in EXIF_FIELDS}
        scale = min(1.0, max_px / max(width, height))
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
