"""The mosaic pipeline's parameters: one typed, validated model, every field with a default.

This module imports only pydantic so that the API can validate a job's options without loading
OpenCV or the stage code.
"""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field


class MosaicConfig(BaseModel):
    """Options of a ``mosaic`` job; a request's ``options`` are merged on top of these defaults."""

    model_config = ConfigDict(extra="forbid")

    device: Literal["auto", "cpu", "cuda"] = "auto"  # where gpu_kernels run; auto: CUDA when present
    threads: int = Field(0, ge=0, le=64)  # threads matching frame pairs on the CPU; 0: one per CPU core
    working_max_px: int = Field(2048, ge=256, le=20000)  # longest side of the working copies, px
    # sift: rotation- and scale-invariant (UAV frames); harris_ncc: Harris corners matched by normalised
    # cross-correlation of windows, for strips whose frames keep their orientation and scale (aerial)
    feature_type: Literal["sift", "harris_ncc"] = "sift"
    ncc_half_window: int = Field(7, ge=2, le=30)  # harris_ncc: window of 2h+1 px around each corner
    ncc_threshold: float = Field(0.85, gt=0.0, lt=1.0)  # harris_ncc: lowest correlation of a match
    max_features: int = Field(6000, ge=100, le=100000)  # SIFT keypoints kept per frame
    ratio_test: float = Field(0.75, gt=0.0, lt=1.0)  # Lowe's nearest/second-nearest distance ratio
    ransac_threshold_px: float = Field(2.0, gt=0.0, le=50.0)  # USAC inlier threshold, working px
    min_inliers: int = Field(25, ge=8)  # a pair with fewer homography inliers is not an overlap
    min_inlier_ratio: float = Field(0.15, ge=0.0, le=1.0)  # inliers / ratio-test matches, same
    max_pair_gap: int = Field(3, ge=1, le=50)  # with GPS: also try frames this far apart in order
    gps_neighbours: int = Field(6, ge=0, le=50)  # with GPS: nearest frames (by position) to try
    exhaustive_max_frames: int = Field(30, ge=2, le=200)  # no GPS: all pairs up to this many frames
    max_tie_points_per_pair: int = Field(400, ge=20, le=5000)  # spread subset used in adjustment
    perspective_damping: float = Field(1000.0, ge=0.0, le=1e6)  # adjustment: cost of perspective drift, 1/px
    gain_compensation: bool = True  # equalise brightness between overlapping frames
    feather_px: float = Field(60.0, ge=1.0, le=2000.0)  # width of the blending ramp at frame edges, px
    block_px: int = Field(1024, ge=256, le=8192)  # output window edge when composing, px
    cog_compression: Literal["deflate", "jpeg", "lzw"] = "deflate"  # COG codec for the mosaic
    min_gps_frames: int = Field(3, ge=2)  # georeference only with at least this many GPS fixes


JOB_KINDS: dict[str, type[BaseModel]] = {"mosaic": MosaicConfig}


def build_config(kind: str, options: dict[str, Any] | None) -> BaseModel:
    """Merge ``options`` over the defaults of ``kind``; raises ``pydantic.ValidationError``."""
    if kind not in JOB_KINDS:
        raise ValueError(f"unknown job kind {kind!r}; known: {sorted(JOB_KINDS)}")
    return JOB_KINDS[kind].model_validate(options or {})
