"""The mosaic pipeline's parameters: one typed, validated model, every field with a default.

This module imports only pydantic so that the API can validate a job's options without loading
OpenCV or the stage code.
"""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator

DistortionTerm = Literal["k1", "k2", "k3", "t1", "t2"]
Convention = Literal["distort_ideal", "restore_ideal"]


class MosaicConfig(BaseModel):
    """Options of a ``mosaic`` job; a request's ``options`` are merged on top of these defaults."""

    model_config = ConfigDict(extra="forbid")

    # planar: frames chained by homographies onto one plane (flat ground, no camera model);
    # ortho: photo-triangulation (bundle adjustment with GPS and GCPs), then every frame is
    # orthorectified onto the ground plane through its adjusted camera
    mode: Literal["planar", "ortho"] = "planar"
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
    # -- mode "ortho" only ----------------------------------------------------------------------
    camera: dict[str, Any] | None = None  # a calibrated camera (camera JSON); None: from EXIF focal length
    self_calibrate: list[Literal["focal", "k1", "k2"]] = ["focal", "k1", "k2"]  # intrinsics the adjustment refines
    gps_sigma_m: float = Field(5.0, gt=0.0, le=1000.0)  # accuracy of the frames' GPS positions, m
    gcp_sigma_m: float = Field(0.02, gt=0.0, le=100.0)  # accuracy of the ground control points, m
    checkpoints: list[str] = []  # GCP names held out of the adjustment and reported as check points
    robust_loss_px: float = Field(2.0, gt=0.0, le=50.0)  # Huber scale of reprojection residuals, px
    outlier_px: float = Field(4.0, gt=0.0, le=100.0)  # observations beyond this after a first solve are dropped
    ground_elevation_m: float | None = None  # ortho plane height; None: median height of the tie points
    max_ground_range: float = Field(4.0, gt=0.0, le=100.0)  # ortho: clip frames to this many flying heights


class CalibrationConfig(BaseModel):
    """Options of a ``calibration`` job: one camera from chessboards, marked points or straight lines."""

    model_config = ConfigDict(extra="forbid")

    # chessboard: corners found by OpenCV; markers: image points marked by hand with their board
    # coordinates; plumb_line: distortion only, from points along lines that are straight in the world
    method: Literal["chessboard", "markers", "plumb_line"] = "chessboard"
    pattern: tuple[int, int] = (9, 6)  # chessboard inner corners (columns, rows)
    square_mm: float = Field(25.0, gt=0.0, le=10000.0)  # chessboard square edge, mm
    convention: Convention = "distort_ideal"  # how the distortion terms are applied (see camera.py)
    terms: list[DistortionTerm] = ["k1", "k2", "t1", "t2", "k3"]  # distortion terms to estimate
    markers: list[Marks] = []  # marked points per image; for chessboard jobs they replace detected corners
    lines: list[list[tuple[float, float]]] = []  # plumb_line: pixel points along each straight line
    image_size: tuple[int, int] | None = None  # plumb_line without images: (width, height) px
    camera: dict[str, Any] | None = None  # plumb_line: intrinsics to normalise with (camera JSON)

    _pattern = field_validator("pattern")(lambda v: _check_pattern(v))


class Marks(BaseModel):
    """Points marked on one image: pixel positions and their board coordinates (mm)."""

    model_config = ConfigDict(extra="forbid")

    image: str = Field(min_length=1)  # the image's file name as uploaded
    image_points: list[tuple[float, float]] = []  # pixel (x, y)
    board_points: list[tuple[float, float, float]] = []  # board (X, Y, Z), mm; same order
    remove: bool = False  # true: drop this image from the solve


class StereoCalibrationConfig(BaseModel):
    """Options of a ``stereo_calibration`` job: a two-camera rig from paired chessboard images."""

    model_config = ConfigDict(extra="forbid")

    pattern: tuple[int, int] = (9, 6)  # chessboard inner corners (columns, rows)
    square_mm: float = Field(25.0, gt=0.0, le=10000.0)  # chessboard square edge, mm
    convention: Convention = "distort_ideal"  # distortion convention of both cameras
    terms: list[DistortionTerm] = ["k1", "k2", "t1", "t2", "k3"]  # distortion terms per camera
    left_camera: dict[str, Any] | None = None  # fixed intrinsics (camera JSON); None: calibrated here
    right_camera: dict[str, Any] | None = None  # same, right camera

    _pattern = field_validator("pattern")(lambda v: _check_pattern(v))


def _check_pattern(pattern: tuple[int, int]) -> tuple[int, int]:
    if min(pattern) < 2 or max(pattern) > 100:
        raise ValueError("a chessboard pattern counts 2-100 inner corners per side, e.g. [9, 6]")
    return pattern


CalibrationConfig.model_rebuild()

JOB_KINDS: dict[str, type[BaseModel]] = {"mosaic": MosaicConfig, "calibration": CalibrationConfig,
                                         "stereo_calibration": StereoCalibrationConfig}


def build_config(kind: str, options: dict[str, Any] | None) -> BaseModel:
    """Merge ``options`` over the defaults of ``kind``; raises ``pydantic.ValidationError``."""
    if kind not in JOB_KINDS:
        raise ValueError(f"unknown job kind {kind!r}; known: {sorted(JOB_KINDS)}")
    return JOB_KINDS[kind].model_validate(options or {})
