"""Stage ``load_images``: decode every input frame once and keep a downscaled working copy; a part per photo
(libjpeg, rasterio and cv2.resize release the GIL, so a process's threads decode several at once)."""

from __future__ import annotations

import math
from typing import Any

from workers.config import MosaicConfig
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


PART_UNIT = "frame"  # what a part is, in the progress


def plan(ws: JobWorkspace, cfg: MosaicConfig) -> list[str]:
    """A part per input photo."""
    return [f"{k:05d}" for k in range(len(ws.load_inputs()))]


def run_part(ws: JobWorkspace, cfg: MosaicConfig, key: str) -> dict[str, Any]:
    """Decode photo ``key`` once; write ``work/frame_NNNN.npy``; its record is the ``Frame`` or why not.

    A JPEG is decoded whole (the largest array of the stage, one per thread at a time); a TIFF is averaged down
    block by block, never decoded whole.
    """
    k = int(key)
    item = ws.load_inputs()[k]
    max_px = cfg.working_max_px
    if cfg.mode == "strip":  # a pyramid level of the frame: 1/strip_reduction of its longest side
        max_px = max(1, math.ceil(max(item["width"], item["height"]) / cfg.strip_reduction))
    found = read_reduced(item["path"], max_px)
    if found is None:
        return {"rejected": RejectedFrame(k, item["name"], "could not be decoded").to_json()}
    working, (width, height) = found
    ws.save_working_image(k, working)
    metadata = {name: item.get(name) for name in EXIF_FIELDS}
    scale = min(1.0, max_px / max(width, height))
    frame = Frame(k, item["name"], item["path"], width, height, working.shape[1], working.shape[0], scale, **metadata)
    return {"frame": frame.to_json()}


def finish(
    ws: JobWorkspace, cfg: MosaicConfig, records: dict[str, dict[str, Any]], *, progress: ProgressFn = noop_progress
) -> dict[str, Any]:
    """Write ``frames.json``: the frames decoded, and those that could not be."""
    frames = [Frame.from_json(r["frame"]) for r in records.values() if "frame" in r]
    rejected = [RejectedFrame.from_json(r["rejected"]) for r in records.values() if "rejected" in r]
    if len(frames) < 2:
        raise PipelineError(f"only {len(frames)} of {len(records)} frames could be decoded; a mosaic needs 2")
    ws.save_frames(frames, rejected)
    progress(1.0, f"frame {len(records)}/{len(records)}")
    return {"frames": len(frames), "rejected": len(rejected)}
