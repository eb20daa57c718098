"""Every job kind's parameters: one typed, validated model per kind (``JOB_KINDS``: mosaic, calibration,
stereo calibration, crack survey, stereo DEM), every field with a default; ``build_config`` merges a job's
options on top.

This module imports only pydantic (and ``core.kinds``) so that the API can validate a job's options
without loading OpenCV or the stage code.
"""

from __future__ import annotations

import math
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationInfo, field_validator, model_validator

from core.kinds import JobKind

DistortionTerm = Literal["k1", "k2", "k3", "t1", "t2"]
Convention = Literal["distort_ideal", "restore_ideal"]

# -- Bounds on every option (a number outside them, NaN or Infinity is refused with the option named) ----
MAX_ID = 2**63 - 1  # ids of flights and jobs: signed 64-bit integers, as the database holds them
MAX_NAME_CHARS = 255  # a photo's, mesh's or GCP's name
MAX_PIXEL = 1e6  # |pixel coordinate|, px; photos are at most 100 000 px a side
MAX_MM = 1e7  # |board or specimen coordinate|, mm (10 km)
MAX_PHOTOS = 1000  # photos named by one job's options (a request holds at most 1000 files)
MAX_POINTS = 10_000  # points marked on one photo or along one line (a 100 x 100 chessboard)
MAX_CONTROL_POINTS = 1000  # control points of one photo of a crack survey
MAX_LOAD_STEPS = 100  # load steps (options.stages) of one crack survey
MAX_CHECKPOINTS = 1000  # GCP names held out as check points
MAX_LINES = 1000  # straight lines of a plumb-line calibration
MAX_RASTER_PIXELS = 200_000_000  # a crack survey's rectified raster; the same limit as rectify_specimen's

Name = Annotated[str, Field(min_length=1, max_length=MAX_NAME_CHARS)]
Pixel = Annotated[float, Field(ge=-MAX_PIXEL, le=MAX_PIXEL)]
Millimetres = Annotated[float, Field(ge=-MAX_MM, le=MAX_MM)]
Side = Annotated[int, Field(ge=1, le=100_000)]  # a photo's width or height, px
# every config model: unknown options and NaN or Infinity refused, and the defaults held to the bounds too
OPTIONS = ConfigDict(extra="forbid", allow_inf_nan=False, validate_default=True)


ORB_FEATURES = 2000  # MosaicConfig.max_features unless given, for ORB (0.6 MP registration copies)
# MosaicConfig.working_max_px's default; the pixel thresholds of matching and adjustment are set for working copies
# of this size and grow with larger ones (MosaicConfig.threshold_scale)
WORKING_MAX_PX = 2048


class MosaicConfig(BaseModel):
    """Options of a ``mosaic`` job; a request's ``options`` are merged on top of these defaults."""

    model_config = OPTIONS

    # planar: frames chained by homographies onto one plane (flat ground, no camera model);
    # ortho: photo-triangulation (bundle adjustment with GPS and GCPs), then every frame is
    # orthorectified onto the ground plane through its adjusted camera
    # strip: planar, for aerial strip frames (long across track, e.g. 75000 x 1800): tie points coarse to
    # fine on a pyramid with the spread criterion, then at native resolution read by window
    mode: Literal["planar", "ortho", "strip"] = "planar"
    device: Literal["auto", "cpu", "cuda"] = "auto"  # where gpu_kernels run; auto: CUDA when present
    threads: int = Field(
        0, ge=0, le=64
    )  # threads for per-frame and per-pair work; 0: one per CPU core (GPU strip pairs: 1)
    working_max_px: int = Field(WORKING_MAX_PX, ge=256, le=20000)  # longest side of the working copies, px
    # planar mode: longest side the features are found at, px (about 0.6 MP per frame, as cv2.Stitcher's
    # registration_resol); their tie points are refined on the working copies. Ortho mode: ortho_registration_max_px
    registration_max_px: int = Field(1024, ge=128, le=20000)
    # orb: binary corners matched by Hamming distance, about 10x cheaper than SIFT (cv2.Stitcher's default); the
    # default in planar mode, where tie points are refined on the working copies, and frames it cannot connect
    # are matched again with SIFT; sift: rotation- and scale-invariant, at working precision (the default in
    # ortho mode); harris_ncc: Harris corners matched by normalised cross-correlation of windows, for strips
    # whose frames keep their orientation and scale (aerial)
    feature_type: Literal["sift", "orb", "harris_ncc"] = "sift"
    ncc_half_window: int = Field(7, ge=2, le=30)  # harris_ncc: window of 2h+1 px around each corner
    ncc_threshold: float = Field(0.85, gt=0.0, lt=1.0)  # harris_ncc: lowest correlation of a match
    max_features: int = Field(6000, ge=100, le=100000)  # keypoints kept per frame (ORB's default: 2000)
    ratio_test: float = Field(0.75, gt=0.0, lt=1.0)  # Lowe's nearest/second-nearest distance ratio
    # USAC inlier threshold, px of a WORKING_MAX_PX working copy (larger ones scale it: threshold_scale)
    ransac_threshold_px: float = Field(2.0, gt=0.0, le=50.0)
    min_inliers: int = Field(25, ge=8, le=100000)  # a pair with fewer homography inliers is not an overlap
    min_inlier_ratio: float = Field(0.15, ge=0.0, le=1.0)  # inliers / ratio-test matches, same
    max_pair_gap: int = Field(3, ge=1, le=50)  # with GPS: also try frames this far apart in order
    gps_neighbours: int = Field(6, ge=0, le=50)  # with GPS: nearest frames (by position) to try
    exhaustive_max_frames: int = Field(30, ge=2, le=200)  # no GPS: all pairs up to this many frames
    # planar mode: pairs that descriptor matching did not accept but that the accepted ones say overlap are
    # matched again by correlation where that alignment predicts (the cross-links between flight lines)
    guided_matching: bool = True
    guided_min_overlap: float = Field(0.03, gt=0.0, le=1.0)  # least predicted overlap worth it, share of a frame
    max_tie_points_per_pair: int = Field(400, ge=20, le=5000)  # spread subset used in adjustment
    # guided tie points a frame's pairs share: a pair measures this shared among the pairs of the less busy of
    # its two frames (at most max_tie_points_per_pair): a frame in many overlaps needs fewer of each
    tie_points_per_frame: int = Field(1200, ge=40, le=100000)
    perspective_damping: float = Field(1000.0, ge=0.0, le=1e6)  # adjustment: cost of perspective drift, 1/px
    gain_compensation: bool = True  # equalise brightness between overlapping frames
    # undo the lens' radial fall-off (vignetting), estimated from the overlaps (one camera for all frames)
    vignetting_correction: bool = False
    feather_px: float = Field(60.0, ge=1.0, le=2000.0)  # width of the blending ramp at frame edges, px
    # feather: every overlap cross-faded over feather_px; multiband: seams cut through the overlaps where the
    # frames agree (graph cut on a low-resolution render), then Laplacian bands blended across them
    blend: Literal["feather", "multiband"] = "feather"
    blend_bands: int = Field(5, ge=1, le=8)  # multiband: pyramid levels; the coarsest blends over ~2^bands px
    # feather: cut seams anyway (about 1.2 s on the Brighton strip) to report the seam visibility on them, as a
    # multiband mosaic would be cut (bench/seams.py compares the blends so); a multiband mosaic always has them
    measure_seams: bool = False
    # output window edge when composing, px: 512 is the COG tile; 1024 took 25 % more peak memory, no less time
    block_px: int = Field(512, ge=256, le=8192)
    # COG codec for the mosaic: deflate (lossless, every reader), zstd (lossless, ~30 % faster to write, GDAL
    # 2.3+ readers), lzw, jpeg (quality 90, lossy, ~6x smaller)
    cog_compression: Literal["deflate", "zstd", "jpeg", "lzw"] = "deflate"
    # planar mode: the mosaic's pixels. working: those of the working copies (working_max_px on the longest
    # side, about half a 4000 px photo's); native: the photos' own, composed from the full photos (about 4x
    # the pixels and the time of composing; the alignment is the same)
    output_resolution: Literal["working", "native"] = "working"
    min_gps_frames: int = Field(3, ge=2, le=10000)  # georeference only with at least this many GPS fixes
    # accuracy of the frames' GPS positions, m; both modes' adjustments weigh the fixes by it
    gps_sigma_m: float = Field(5.0, gt=0.0, le=1000.0)
    # -- mode "strip" only ----------------------------------------------------------------------
    strip_reduction: int = Field(8, ge=1, le=64)  # working copies at 1/this of the frames (working_max_px unused)
    strip_tie_points: int = Field(400, ge=20, le=20000)  # native-resolution tie points sought per pair
    strip_min_spread: float = Field(0.5, gt=0.0, le=1.0)  # inliers must span this share of the overlap's length
    # frames joined across their width from this many CCD sub-images of equal width (32 for the source camera): the
    # gain step at each join is measured in the frames' own rows and undone; 0: none
    ccd_segments: int = Field(0, ge=0, le=4096)
    # how square each frame's ground pixels are at its centre (the aspect and shear of its map there), a prior of
    # the adjustment with GPS: a near-nadir survey camera's are square to 1e-4 (1 degree of tilt gives 8e-5).
    # At 50 % forward overlap the tie points leave each frame's width free and GPS only fixes centres: without
    # it, a 305-frame strip's corners were 822 px off; with it, 6.8. 0: no prior (oblique frames)
    strip_square_pixels: float = Field(1e-4, ge=0.0, le=1.0)
    # -- mode "ortho" only ----------------------------------------------------------------------
    camera: dict[str, Any] | None = None  # a calibrated camera (camera JSON); None: from EXIF focal length
    # intrinsics the adjustment refines
    self_calibrate: list[Literal["focal", "k1", "k2"]] = Field(["focal", "k1", "k2"], max_length=3)
    gcp_sigma_m: float = Field(0.02, gt=0.0, le=100.0)  # accuracy of the ground control points, m
    # GCP names held out of the adjustment and reported as check points
    checkpoints: list[Name] = Field([], max_length=MAX_CHECKPOINTS)
    # longest side the features are found at, px: the working copies up to it, a copy of this size of larger ones
    # (the bundle adjustment needs no finer ties than the default working copies give: on the Brighton strip SIFT's
    # 6000 strongest features of 4000 px copies were grass and noise, and 3 of its 6 frames were left out)
    ortho_registration_max_px: int = Field(WORKING_MAX_PX, ge=128, le=20000)
    # Huber scale of reprojection residuals, and observations beyond outlier_px after a first solve are dropped:
    # px of a WORKING_MAX_PX working copy (larger ones scale them: threshold_scale)
    robust_loss_px: float = Field(2.0, gt=0.0, le=50.0)
    outlier_px: float = Field(4.0, gt=0.0, le=100.0)
    # ortho plane height, m (the GPS altitudes' datum); None: median height of the tie points
    ground_elevation_m: float | None = Field(None, ge=-1000.0, le=10000.0)
    # what frames are projected onto (relief displacement removed): dense, the tie points' surface refined by
    # dense stereo (SGBM) between neighbouring frames where they overlap (halves its height error on a rendered
    # terrain for 1.7 s, 8 % of the pipeline, on the Brighton strip); tie_points, a surface gridded and
    # smoothed from the adjusted tie points; plane, the plane at ground_elevation_m (relief displacement kept)
    ortho_surface: Literal["dense", "tie_points", "plane"] = "dense"
    # ortho_surface dense: frames are matched at a reduced size, this many px on their longest side
    ortho_dense_px: int = Field(768, ge=128, le=4096)
    max_ground_range: float = Field(4.0, gt=0.0, le=100.0)  # ortho: clip frames to this many flying heights

    def threshold_scale(self, working_px: int) -> float:
        """The factor on the pixel thresholds of matching and adjustment (``ransac_threshold_px``; in ortho mode
        ``robust_loss_px``, ``outlier_px`` and the reconstruction's own) for working copies ``working_px`` on their
        longest side: 1 up to ``WORKING_MAX_PX``, for which they are set, growing with larger copies.

        Features are found on copies of at most ``registration_max_px`` (ortho: ``ortho_registration_max_px``),
        which do not grow with the working copies, and a scene's relief shows as more working pixels of parallax
        in finer ones: at 4000 px and 2 px the Brighton strip's planar pairs kept 15-62 inliers and 2 of its 6
        frames were lost; at 3.9 px all 6, tie RMS 1.35 photo px (1.73 at 2048). A strip's working copies are
        pyramid levels and its tie points native: its thresholds stay as given."""
        if self.mode == "strip":
            return 1.0
        return max(1.0, working_px / WORKING_MAX_PX)

    def inlier_px(self, working_px: int) -> float:
        """``ransac_threshold_px`` on working copies ``working_px`` on their longest side (:meth:`threshold_scale`)."""
        return self.ransac_threshold_px * self.threshold_scale(working_px)

    @model_validator(mode="after")
    def _strips_are_native(self) -> MosaicConfig:
        # a strip's working copy is a reduced pyramid level: its mosaic is at the frames' own resolution
        # unless asked otherwise
        if self.mode == "strip" and "output_resolution" not in self.model_fields_set:
            self.output_resolution = "native"
        # a strip's tie points, measured at native resolution, fix each frame's perspective better than the
        # chained pairwise start the damping would hold it to (12 frames of 20000 px: corners within 0.2 px of
        # the truth undamped, 5.3 px damped)
        if self.mode == "strip" and "perspective_damping" not in self.model_fields_set:
            self.perspective_damping = 0.0
        return self

    @model_validator(mode="after")
    def _planar_registers_with_orb(self) -> MosaicConfig:
        # planar mode refines tie points on the working copies, so ORB's coarser corners cost nothing there
        # (Brighton strip: 1.15 px of the photos against SIFT's 1.77, all 6 frames, 1/10 of detecting time)
        if self.mode == "planar" and "feature_type" not in self.model_fields_set:
            self.feature_type = "orb"
        if self.feature_type == "orb" and "max_features" not in self.model_fields_set:
            self.max_features = ORB_FEATURES
        return self

    @model_validator(mode="after")
    def _native_is_planar(self) -> MosaicConfig:
        if self.output_resolution == "native" and self.mode == "ortho":
            raise ValueError(
                "output_resolution 'native' is for planar mosaics; ortho mosaics are rectified from the "
                "working copies (raise working_max_px for a finer orthophoto)"
            )
        return self


class CalibrationConfig(BaseModel):
    """Options of a ``calibration`` job: one camera from chessboards, marked points or straight lines."""

    model_config = OPTIONS

    # chessboard: corners found by OpenCV; markers: image points marked by hand with their board
    # coordinates; plumb_line: distortion only, from points along lines that are straight in the world
    method: Literal["chessboard", "markers", "plumb_line"] = "chessboard"
    pattern: tuple[int, int] = (9, 6)  # chessboard inner corners (columns, rows)
    square_mm: float = Field(25.0, gt=0.0, le=10000.0)  # chessboard square edge, mm
    convention: Convention = "distort_ideal"  # how the distortion terms are applied (see camera.py)
    terms: list[DistortionTerm] = Field(["k1", "k2", "t1", "t2", "k3"], max_length=5)  # distortion terms to estimate
    # marked points per image; for chessboard jobs they replace detected corners
    markers: list[Marks] = Field([], max_length=MAX_PHOTOS)
    # plumb_line: pixel points along each straight line
    lines: list[Annotated[list[tuple[Pixel, Pixel]], Field(max_length=MAX_POINTS)]] = Field([], max_length=MAX_LINES)
    # plumb_line without images: (width, height) px
    image_size: tuple[Side, Side] | None = None
    camera: dict[str, Any] | None = None  # plumb_line: intrinsics to normalise with (camera JSON)

    _pattern = field_validator("pattern")(lambda v: _check_pattern(v))


class Marks(BaseModel):
    """Points marked on one image: pixel positions and their board coordinates (mm)."""

    model_config = OPTIONS

    image: Name  # the image's file name as uploaded
    image_points: list[tuple[Pixel, Pixel]] = Field([], max_length=MAX_POINTS)  # pixel (x, y)
    # board (X, Y, Z), mm; same order
    board_points: list[tuple[Millimetres, Millimetres, Millimetres]] = Field([], max_length=MAX_POINTS)
    remove: bool = False  # true: drop this image from the solve


class StereoCalibrationConfig(BaseModel):
    """Options of a ``stereo_calibration`` job: a two-camera rig from paired chessboard images."""

    model_config = OPTIONS

    pattern: tuple[int, int] = (9, 6)  # chessboard inner corners (columns, rows)
    square_mm: float = Field(25.0, gt=0.0, le=10000.0)  # chessboard square edge, mm
    convention: Convention = "distort_ideal"  # distortion convention of both cameras
    terms: list[DistortionTerm] = Field(["k1", "k2", "t1", "t2", "k3"], max_length=5)  # distortion terms per camera
    left_camera: dict[str, Any] | None = None  # fixed intrinsics (camera JSON); None: calibrated here
    right_camera: dict[str, Any] | None = None  # same, right camera
    # marked points per photo (by its name): they replace its found corners, or remove: true leaves it out
    markers: list[Marks] = Field([], max_length=MAX_PHOTOS)

    _pattern = field_validator("pattern")(lambda v: _check_pattern(v))


def _check_pattern(pattern: tuple[int, int]) -> tuple[int, int]:
    if min(pattern) < 2 or max(pattern) > 100:
        raise ValueError("a chessboard pattern counts 2-100 inner corners per side, e.g. [9, 6]")
    return pattern


Point = tuple[Millimetres, Millimetres, Millimetres]  # model (X, Y, Z), mm


class Specimen(BaseModel):
    """The specimen's model: a plate (X right, Y down, Z = 0 on its surface, mm) or a triangle mesh in mm."""

    model_config = OPTIONS

    width_mm: float | None = Field(None, gt=0.0, le=100000.0)  # plate: extent along X, mm
    height_mm: float | None = Field(None, gt=0.0, le=100000.0)  # plate: extent along Y, mm
    # mesh: the uploaded model file's name (OBJ, PLY or STL, mm)
    mesh: str | None = Field(None, min_length=1, max_length=MAX_NAME_CHARS)
    # mesh: the plane it is rectified onto, as three model points (origin, toward +x, on the +y side);
    # None: the surface's best-fit plane
    plane: tuple[Point, Point, Point] | None = None

    @model_validator(mode="after")
    def _one_model(self) -> Specimen:
        plate = self.width_mm is not None and self.height_mm is not None
        if self.mesh is None and not plate:
            raise ValueError("give width_mm and height_mm for a plate, or mesh (an uploaded model file)")
        if self.mesh is not None and (self.width_mm is not None or self.height_mm is not None):
            raise ValueError("a mesh specimen takes its size from the model: leave out width_mm and height_mm")
        if self.mesh is None and self.plane is not None:
            raise ValueError("plane applies to a mesh specimen only")
        return self


class ControlPoint(BaseModel):
    """A point marked on a photo and its position on the specimen."""

    model_config = OPTIONS

    pixel: tuple[Pixel, Pixel]  # photo pixel (x, y), (0, 0) the centre of the first pixel
    model: Point  # specimen (X, Y, Z), mm; Z = 0 on the surface


class SurveyPhoto(BaseModel):
    """One photo of a load stage and its control points."""

    model_config = OPTIONS

    image: Name  # the photo's file name as uploaded
    control_points: list[ControlPoint] = Field(max_length=MAX_CONTROL_POINTS)  # at least 4, not all on one line


class LoadStage(BaseModel):
    """The photos taken at one load."""

    model_config = OPTIONS

    label: str = Field(min_length=1, max_length=100)  # e.g. "0 kN", "stage 2"
    load: float | None = Field(None, ge=-1e12, le=1e12)  # the applied load, in the user's unit; reported as given
    photos: list[SurveyPhoto] = Field(min_length=1, max_length=MAX_PHOTOS)


class CrackSurveyConfig(BaseModel):
    """Options of a ``crack_survey`` job: cracks of a planar specimen measured in mm at each load stage."""

    model_config = OPTIONS

    camera: dict[str, Any]  # the calibrated camera (camera JSON) that took every photo
    # the calibration job the camera came from: a request may name it instead of giving camera, and the
    # API copies that job's camera into camera, so the survey keeps the camera it was measured with
    calibration_job: int | None = Field(None, ge=1, le=MAX_ID)
    specimen: Specimen
    # in load order; each stage is compared with the one before
    stages: list[LoadStage] = Field(min_length=1, max_length=MAX_LOAD_STEPS)
    # resolution of the rectified specimen images (COGs, overlays), mm per px; None: the photos' own sampling
    # on the specimen. Cracks are detected and measured on a raster set by the photos alone (below), so
    # counts and lengths do not depend on it
    mm_per_px: float | None = Field(None, ge=0.005, le=50.0)
    # the detection raster is this many times finer than the photos' sampling on the specimen (>= 1: a
    # crack one photo pixel wide spans at least one raster pixel)
    detection_oversampling: float = Field(1.25, ge=1.0, le=4.0)
    max_rms_px: float = Field(5.0, gt=0.0, le=100.0)  # a photo whose control points fit worse fails the job, px
    # how a stage with several photos is composed: at each point the photo that sees it most
    # frontally at the finest resolution ("best"), or the mean of all photos that see it ("average")
    compose: Literal["best", "average"] = "best"
    threshold_low: float | None = Field(None, gt=0.0, lt=1.0)  # hysteresis low on crack probability; None: model's
    threshold_high: float | None = Field(None, gt=0.0, lt=1.0)  # hysteresis high; None: the model's tuned value
    # a detected crack whose pixels are (median) less than this fraction darker than the coating around
    # it is dropped: the detector normalises contrast away and can take interpolated grain for a crack
    min_crack_contrast: float = Field(0.08, ge=0.0, lt=1.0)
    min_crack_length_mm: float = Field(1.0, ge=0.0, le=10000.0)  # shorter cracks are dropped, mm
    # strip along the specimen's edges where nothing is detected, mm: the plate's edge, blurred over a few
    # photo pixels (mm apiece in an oblique view), is a dark line
    edge_margin_mm: float = Field(3.0, ge=0.0, le=1000.0)
    match_tolerance_mm: float = Field(1.0, gt=0.0, le=100.0)  # a crack continues one of the stage before
    # if it runs within this distance of it, mm
    min_growth_mm: float = Field(2.0, ge=0.0, le=10000.0)  # smaller length gains are "unchanged", mm
    cog_compression: Literal["deflate", "zstd", "jpeg", "lzw"] = "deflate"  # COG codec of the rectified images

    @field_validator("stages")
    @classmethod
    def _check_photos(cls, stages: list[LoadStage], info: ValidationInfo) -> list[LoadStage]:
        specimen = info.data.get("specimen")  # absent when it failed its own validation
        seen: set[str] = set()
        for s, stage in enumerate(stages):
            for p, photo in enumerate(stage.photos):
                if photo.image in seen:
                    raise ValueError(f"photo {photo.image!r} is named twice; each photo belongs to one stage")
                seen.add(photo.image)
                if specimen is not None:
                    _check_control_points(f"stage {s} photo {p} ({photo.image})", photo.control_points, specimen)
        return stages

    @field_validator("mm_per_px")
    @classmethod
    def _check_raster(cls, mm_per_px: float | None, info: ValidationInfo) -> float | None:
        specimen = info.data.get("specimen")  # a mesh's size is known once the mesh is read (the API)
        if mm_per_px is None:  # the photos' sampling: known once they are oriented (rectify_specimen checks)
            return None
        if specimen is not None and specimen.width_mm is not None and specimen.height_mm is not None:
            check_raster_size(specimen.width_mm, specimen.height_mm, mm_per_px)
        return mm_per_px


def check_raster_size(width_mm: float, height_mm: float, mm_per_px: float) -> None:
    """``ValueError`` when the rectified raster of a specimen this large is over ``MAX_RASTER_PIXELS``.

    Its shape is ``specimen.raster_shape``'s (pixel centres every ``mm_per_px`` from 0 to the extents)."""
    rows = math.floor(height_mm / mm_per_px + 1e-9) + 1
    cols = math.floor(width_mm / mm_per_px + 1e-9) + 1
    if rows * cols > MAX_RASTER_PIXELS:
        raise ValueError(
            f"the specimen is {cols} x {rows} px at {mm_per_px} mm/px, more than {MAX_RASTER_PIXELS} px; "
            "choose a coarser mm_per_px"
        )


MIN_CONTROL_POINTS = 4  # a plane-to-photo mapping has 8 degrees of freedom
# a pose from points on a curved surface: 6 unknowns, and points off one plane to pin the depth
MIN_MESH_CONTROL_POINTS = 6


def _check_control_points(where: str, points: list[ControlPoint], specimen: Specimen) -> None:
    """Enough points (4 on a plate, 6 on a mesh), on a plate inside it, and not all on one line.

    Whether a mesh's points lie on its surface is checked where the mesh is read (the API)."""
    needed = MIN_CONTROL_POINTS if specimen.mesh is None else MIN_MESH_CONTROL_POINTS
    if len(points) < needed:
        raise ValueError(f"{where}: {len(points)} control point(s); at least {needed} are needed")
    if specimen.width_mm is not None and specimen.height_mm is not None:
        _check_on_plate(where, points, specimen.width_mm, specimen.height_mm)
    if _collinear([p.model for p in points]):
        raise ValueError(f"{where}: the control points lie on one line; they must span the specimen's surface")


def _check_on_plate(where: str, points: list[ControlPoint], width_mm: float, height_mm: float) -> None:
    tolerance = 1e-6 * max(width_mm, height_mm)
    for k, point in enumerate(points):
        x, y, z = point.model
        if not (
            -tolerance <= x <= width_mm + tolerance and -tolerance <= y <= height_mm + tolerance and abs(z) <= tolerance
        ):
            raise ValueError(
                f"{where}: control point {k} at model {list(point.model)} is outside the specimen "
                f"(0..{width_mm} x 0..{height_mm} mm, Z = 0)"
            )


def _collinear(model: list[tuple[float, float, float]]) -> bool:
    """True when no point is farther than 0.1% of their span from the line through the two farthest apart.

    (Plain Python: this module imports only pydantic.)
    """
    far = max(((a, b) for a in model for b in model), key=lambda ab: math.dist(*ab))
    span = math.dist(*far)
    if span == 0.0:
        return True
    direction = [(q - p) / span for p, q in zip(*far, strict=True)]
    off = max(
        math.dist(p, [f + t * d for f, d in zip(far[0], direction, strict=True)])
        for p in model
        for t in [sum((pi - fi) * d for pi, fi, d in zip(p, far[0], direction, strict=True))]
    )
    return off <= 1e-3 * span


MAX_DISPARITY_PX = 4096  # |disparity| of a stereo pair, px
MAX_STEREO_PIXELS = 40_000_000  # each photo of a stereo DEM; larger pairs are cut to the area of interest first
Height = Annotated[float, Field(ge=-1000.0, le=10000.0)]  # a ground height, m above the ellipsoid


class StereoDemConfig(BaseModel):
    """Options of a ``stereo_dem`` job: a disparity map of two photos of the same ground and, when they are
    georeferenced (RPCs), a DSM."""

    model_config = OPTIONS

    # how the pair's geometry is known. rectified: rows are already epipolar lines; rig: a calibrated stereo
    # rig took it (rig_job); uncalibrated: from a fundamental matrix of matched features; rpc: both photos are
    # GeoTIFFs with RPC metadata (satellite products). auto: rig when rig_job is given, rectified when
    # rectified is true, rpc when both photos carry RPCs, uncalibrated otherwise (the API decides)
    geometry: Literal["auto", "rectified", "rig", "uncalibrated", "rpc"] = "auto"
    rectified: bool = False  # the photos are rectified already: geometry "rectified"
    rig_job: int | None = Field(None, ge=1, le=MAX_ID)  # a finished stereo-rig job whose rig took the pair
    rig: dict[str, Any] | None = None  # the rig (StereoRig JSON); the API copies it from rig_job
    # sgbm: OpenCV's semi-global matcher, tuned, with our checks; local: the source work's windowed 2-D search
    # with a soft epipolar constraint (gpu_kernels.stereo_local), on CUDA where device allows
    method: Literal["sgbm", "local"] = "sgbm"
    device: Literal["auto", "cpu", "cuda"] = "auto"  # where the local method runs; auto: CUDA when present
    # disparities searched, d = x_left - x_right in rectified px: [min_disparity, min_disparity + num_disparities);
    # None: from SIFT matches of the rectified pair (and, for rpc, the heights its RPCs allow)
    min_disparity: int | None = Field(None, ge=-MAX_DISPARITY_PX, le=MAX_DISPARITY_PX)
    num_disparities: int | None = Field(None, ge=16, le=1024)
    fill: bool = True  # fill occlusions and rejected matches from the background side, and DSM holes (flagged)
    # rpc: lowest and highest ground height, m above the ellipsoid; None: the RPCs' own validity range
    height_range_m: tuple[Height, Height] | None = None
    dsm_resolution_m: float | None = Field(None, ge=0.01, le=1000.0)  # DSM cell size, m; None: the left photo's GSD
    # DSM holes are filled this far at most from a cell with a height, m; None: 64 cells
    max_fill_m: float | None = Field(None, gt=0.0, le=100000.0)
    cog_compression: Literal["deflate", "lzw"] = "deflate"  # codec of the output COGs

    @model_validator(mode="after")
    def _one_geometry(self) -> StereoDemConfig:
        if self.rectified and self.geometry not in ("auto", "rectified"):
            raise ValueError(f"rectified: true contradicts geometry {self.geometry!r}")
        if self.rig_job is not None and self.geometry not in ("auto", "rig"):
            raise ValueError(f"rig_job is for geometry 'rig', not {self.geometry!r}")
        if self.rectified and self.rig_job is not None:
            raise ValueError("give rectified: true or rig_job, not both")
        if self.geometry == "rig" and self.rig_job is None and self.rig is None:
            raise ValueError("geometry 'rig' needs rig_job: the id of a finished stereo-rig job")
        if self.min_disparity is not None and self.num_disparities is None:
            raise ValueError("min_disparity needs num_disparities")
        lo_hi = self.height_range_m
        if lo_hi is not None and not lo_hi[1] > lo_hi[0]:
            raise ValueError("height_range_m: give [lowest, highest] with highest above lowest")
        return self

    def resolved_geometry(self, both_have_rpcs: bool) -> str:
        """The geometry ``auto`` stands for, given whether both photos carry RPCs (else ``geometry`` itself)."""
        if self.geometry != "auto":
            return self.geometry
        if self.rectified:
            return "rectified"
        if self.rig_job is not None or self.rig is not None:
            return "rig"
        return "rpc" if both_have_rpcs else "uncalibrated"


CalibrationConfig.model_rebuild()

JOB_KINDS: dict[JobKind, type[BaseModel]] = {
    JobKind.mosaic: MosaicConfig,
    JobKind.calibration: CalibrationConfig,
    JobKind.stereo_calibration: StereoCalibrationConfig,
    JobKind.crack_survey: CrackSurveyConfig,
    JobKind.stereo_dem: StereoDemConfig,
}


def build_config(kind: str, options: dict[str, Any] | None) -> BaseModel:
    """Merge ``options`` over the defaults of ``kind``; raises ``pydantic.ValidationError``."""
    if kind not in JOB_KINDS:
        raise ValueError(f"unknown job kind {str(kind)!r}; known: {sorted(map(str, JOB_KINDS))}")
    return JOB_KINDS[JobKind(kind)].model_validate(options or {})
