"""Stage ``rectify_pair``: a stereo DEM's two photos resampled so that rows are epipolar lines, and the range
of disparities to search.

By ``geometry``: ``rectified`` keeps the photos; ``rig`` rectifies through the calibrated rig
(``cv2.stereoRectify``); ``uncalibrated`` through a fundamental matrix of SIFT matches
(``cv2.stereoRectifyUncalibrated``); ``rpc`` through the affine epipolar geometry the GeoTIFFs' RPC models
give over the ground's heights. The disparity range is the options', else that of SIFT matches of the
rectified pair (for ``rpc`` kept within what the heights allow).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from workers.algorithms.calibration import StereoRig
from workers.algorithms.stereo import (
    Rectification,
    Rpc,
    disparity_range,
    fundamental_from_matches,
    grey8,
    ground_sample_distance,
    height_disparity_range,
    identity_rectification,
    remap_pair,
    rig_rectification,
    rpc_correspondences,
    rpc_rectification,
    same_channels,
    sparse_matches,
    to_8bit_pair,
    uncalibrated_rectification,
    warp_pair,
)
from workers.config import StereoDemConfig
from workers.photo_io import read_photo_array, read_rpcs
from workers.pipeline import PipelineError
from workers.workspace import JobWorkspace, ProgressFn, noop_progress

MAX_MATCH_PIXELS = 60_000_000  # a rectified canvas larger than this is refused
MAX_ESTIMATED_DISPARITIES = 1024  # an estimated range wider than this means the estimate failed

Images = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]  # left, right and what each covers


def run(ws: JobWorkspace, cfg: StereoDemConfig, *, progress: ProgressFn = noop_progress) -> dict[str, Any]:
    """Write the rectified pair and ``rectification.json`` (geometry, homographies, disparity range)."""
    frames = {f["side"]: f for f in ws.load_inputs()}
    raw = [_read(frames[side]) for side in ("left", "right")]
    left, right = same_channels(*to_8bit_pair(raw[0], raw[1]))
    # the API decides auto; a job made otherwise (a test, a script) is decided the same way here
    geometry = cfg.resolved_geometry(all(read_rpcs(Path(f["path"])) is not None for f in frames.values()))
    progress(0.1, f"rectifying ({geometry})")
    extra: dict[str, Any] = {}
    try:
        if geometry == "rectified":
            if left.shape[:2] != right.shape[:2]:
                raise ValueError(f"a rectified pair has one size; left is {_size(left)}, right {_size(right)}")
            rect = identity_rectification(left.shape[1], left.shape[0])
            images: Images = (left, right, np.ones(left.shape[:2], bool), np.ones(right.shape[:2], bool))
        elif geometry == "rig":
            rect, images = _rig(cfg, left, right)
        elif geometry == "uncalibrated":
            rect, images, extra = _uncalibrated(left, right)
        else:
            rect, images, extra = _rpc(cfg, frames, left, right)
    except ValueError as exc:
        raise PipelineError(f"cannot rectify the pair: {exc}") from None
    if rect.width * rect.height > MAX_MATCH_PIXELS:
        raise PipelineError(f"the rectified pair is {rect.width}x{rect.height} px, over {MAX_MATCH_PIXELS} px")
    progress(0.7, "disparity range")
    low, count, source = _disparity_range(cfg, images, extra.pop("heights_range", None))
    ws.save_rectified_pair(*images)
    ws.save_rectification(
        {
            "geometry": geometry,
            "rectification": rect.to_json(),
            "min_disparity": low,
            "num_disparities": count,
            "range_source": source,
            **extra,
        }
    )
    return {
        "geometry": geometry,
        "rectified_size": [rect.width, rect.height],
        "row_residual_px": round(rect.residual_px, 4),
        "min_disparity": low,
        "num_disparities": count,
        "range_source": source,
        **{k: v for k, v in extra.items() if k in ("matches", "inliers", "gsd_m", "heights_m")},
    }


def _read(frame: dict[str, Any]) -> np.ndarray:
    image = read_photo_array(frame["path"])
    if image is None:
        raise PipelineError(f"{frame['name']}: the photo cannot be decoded")
    return image


def _size(image: np.ndarray) -> str:
    return f"{image.shape[1]}x{image.shape[0]} px"


def _rig(cfg: StereoDemConfig, left: np.ndarray, right: np.ndarray) -> tuple[Rectification, Images]:
    rig = StereoRig.from_json(cfg.rig or {})
    for side, image, camera in (("left", left, rig.left), ("right", right, rig.right)):
        if (image.shape[1], image.shape[0]) != (camera.width, camera.height):
            raise ValueError(
                f"the {side} photo is {_size(image)} but the rig's {side} camera {camera.width}x{camera.height}"
            )
    rect, maps = rig_rectification(rig)
    return rect, remap_pair(maps, left, right)


def _uncalibrated(left: np.ndarray, right: np.ndarray) -> tuple[Rectification, Images, dict[str, Any]]:
    pl, pr = sparse_matches(grey8(left), grey8(right))
    fundamental, inliers = fundamental_from_matches(pl, pr)
    rect = uncalibrated_rectification(fundamental, pl[inliers], pr[inliers], (left.shape[1], left.shape[0]))
    extra = {"matches": len(pl), "inliers": int(inliers.sum()), "fundamental": fundamental.tolist()}
    return rect, warp_pair(rect, left, right), extra


def _rpc(
    cfg: StereoDemConfig, frames: dict[str, dict[str, Any]], left: np.ndarray, right: np.ndarray
) -> tuple[Rectification, Images, dict[str, Any]]:
    models = []
    for side in ("left", "right"):
        data = read_rpcs(Path(frames[side]["path"]))
        if data is None:
            raise ValueError(f"the {side} photo {frames[side]['name']} has no RPC metadata")
        models.append(Rpc.from_dict(data))
    rpc_l, rpc_r = models
    heights = cfg.height_range_m or _common_heights(rpc_l, rpc_r)
    size_l = (left.shape[1], left.shape[0])
    corr = rpc_correspondences(rpc_l, rpc_r, size_l, heights)
    rect = rpc_rectification(corr, size_l)
    gsd = ground_sample_distance(rpc_l, (size_l[0] - 1) / 2, (size_l[1] - 1) / 2, 0.5 * (heights[0] + heights[1]))
    extra = {
        "rpcs": [rpc_l.to_json(), rpc_r.to_json()],
        "heights_m": list(heights),
        "gsd_m": gsd,
        "heights_range": height_disparity_range(corr, rect),
    }
    return rect, warp_pair(rect, left, right), extra


def _common_heights(rpc_l: Rpc, rpc_r: Rpc) -> tuple[float, float]:
    """The heights both models are valid for (their union if they do not overlap)."""
    (a, b), (c, d) = rpc_l.height_range, rpc_r.height_range
    lo, hi = max(a, c), min(b, d)
    return (lo, hi) if hi > lo else (min(a, c), max(b, d))


def _disparity_range(
    cfg: StereoDemConfig, images: Images, heights_range: tuple[int, int] | None
) -> tuple[int, int, str]:
    if cfg.num_disparities is not None:
        return cfg.min_disparity or 0, cfg.num_disparities, "options"
    pl, pr = sparse_matches(grey8(images[0]), grey8(images[1]))
    found = disparity_range(pl, pr)
    if heights_range is not None:
        if found is None:
            return heights_range[0], heights_range[1], "heights"
        low = max(found[0], heights_range[0])
        high = min(found[0] + found[1], heights_range[0] + heights_range[1])
        if high > low:
            return low, int(np.ceil((high - low) / 16.0) * 16), "matches within heights"
        return heights_range[0], heights_range[1], "heights"
    if found is None:
        raise PipelineError(
            f"only {len(pl)} features match between the rectified photos, too few to tell the disparity range; "
            "give options.num_disparities (and min_disparity)"
        )
    if found[1] > MAX_ESTIMATED_DISPARITIES:
        raise PipelineError(
            f"the matched features span {found[1]} px of disparity; give options.num_disparities (and min_disparity)"
        )
    return found[0], found[1], "matches"
