"""Request and response schemas of the REST API."""

from __future__ import annotations

from datetime import datetime
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator

from workers.config import MAX_ID, MAX_PHOTOS, Marks, Pixel


class FlightCreate(BaseModel):
    model_config = ConfigDict(extra="forbid")

    name: str = Field(min_length=1, max_length=200)
    description: str = Field("", max_length=5000)

    @field_validator("name", "description")
    @classmethod
    def _no_nul(cls, value: str) -> str:
        if "\x00" in value:  # PostgreSQL's text cannot hold it
            raise ValueError("must not contain NUL characters")
        return value

    @field_validator("name")
    @classmethod
    def _not_blank(cls, value: str) -> str:
        if not value.strip():
            raise ValueError("must not be blank: give the flight a name")
        return value.strip()


class GpsFix(BaseModel):
    lat: float
    lon: float
    alt: float | None = None


class PhotoQuality(BaseModel):
    analysed_px: list[int]  # width, height of the reduced copy measured
    sharpness: float  # variance of the Laplacian of that copy (0-255 brightness)
    mean_brightness: float  # 0-255
    dark_share: float  # share of nearly black pixels
    bright_share: float  # share of clipped white pixels
    phash: str  # 64-bit perceptual hash, hex


class PhotoIssue(BaseModel):
    code: str
    message: str


class ImageOut(BaseModel):
    id: int
    seq: int
    filename: str
    stored_name: str
    size_bytes: int
    width: int
    height: int
    gps: GpsFix | None = None
    focal_length_mm: float | None = None
    focal_length_35mm: float | None = None
    yaw: float | None = None
    pitch: float | None = None
    roll: float | None = None
    # where a job takes the photo's position from: "side_file" (the flight's GPS file), "exif", or None (none)
    gps_source: Literal["side_file", "exif"] | None = None
    position: GpsFix | None = None  # the position a job takes: the GPS file's, else EXIF's
    # what the upload-time check measured (workers.photo_check.measure); None for photos from before the check
    quality: PhotoQuality | None = None
    # what the check finds against the flight's other photos: blurred, under_exposed, over_exposed, no_gps,
    # duplicate, size_mismatch, not_checked; each with why, in words
    issues: list[PhotoIssue] = []
    preview_url: str | None = None  # a reduced JPEG of the photo (?size=32..2048 px, 256 by default), signed


class FlightOut(BaseModel):
    id: int
    name: str
    description: str
    created_at: datetime
    image_count: int


class FlightDetail(FlightOut):
    images: list[ImageOut]
    signature: str | None = None  # exp=...&sig=...: opens the photos' previews to an <img>, without the token


class UploadResult(BaseModel):
    images: list[ImageOut]


class JobCreate(BaseModel):
    model_config = ConfigDict(extra="forbid")

    flight_id: int = Field(ge=1, le=MAX_ID)
    # JobKind.mosaic, spelled as a plain Literal: a Literal of the enum member would validate the same but
    # word its 422 message differently ("Input should be <JobKind.mosaic: 'mosaic'>")
    kind: Literal["mosaic"] = "mosaic"
    options: dict[str, Any] = Field(
        default_factory=dict,
        description="the job's options over their defaults: MosaicConfig (in the schemas) lists every one",
    )


class JobOut(BaseModel):
    id: int
    flight_id: int | None  # None for calibration and crack-survey jobs, whose photos are their own
    kind: str
    status: str
    stage: str
    stages: list[str]
    progress: float
    progress_detail: str
    timings: dict[str, float]
    error: str
    options: dict[str, Any]
    created_at: datetime
    updated_at: datetime
    # what a user must know before trusting a finished job's result (frames left out or placed again, cameras
    # far from their GPS), from its report, so a client can refuse the result: a list (maybe empty) from
    # GET /api/jobs/{id} once the job has succeeded, null where it was not looked up (lists, other states)
    warnings: list[str] | None = None
    # query string ``exp=...&sig=...`` that opens this job's tiles, downloads and event stream without a token
    # (for image tags and EventSource, which cannot send one) until it expires; from GET /api/jobs/{id} only
    signature: str | None = None
    # time left of a queued or running job, from rates measured on it and on earlier jobs of its pipeline
    # (core.eta): {seconds_left, stage_seconds_left, stages: {stage: {seconds_left, basis, unit, units_per_second}}};
    # from GET /api/jobs/{id} and its event stream only; null when finished or nothing is measured yet
    eta: dict[str, Any] | None = None


class OutputOut(BaseModel):
    name: str
    size_bytes: int
    url: str


class OutputsOut(BaseModel):
    outputs: list[OutputOut]
    # every output in one ZIP (GET /api/jobs/{id}/outputs/all.zip), signed; null while the job has none
    all_zip_url: str | None = None


class JobResultOut(BaseModel):
    """A calibration, stereo-rig or crack-survey job and, once it has one, its result: the camera or rig
    JSON with RMS and per-point errors, or the survey's report."""

    job: JobOut
    result: dict[str, Any] | None = None


class MarksUpdate(BaseModel):
    model_config = ConfigDict(extra="forbid")

    markers: list[Marks] = Field(min_length=1, max_length=MAX_PHOTOS)  # per photo: new marks, or remove: true


class VolumeRequest(BaseModel):
    """A polygon on a stereo DEM's DSM and the base its volume is measured from."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    # (lon, lat) vertices, WGS 84 degrees; the ring is closed for you
    polygon: list[tuple[Annotated[float, Field(ge=-180, le=180)], Annotated[float, Field(ge=-90, le=90)]]] = Field(
        min_length=3, max_length=1000
    )
    # fit: a plane through the surface along the polygon's edge; lowest: the lowest of it; a number: that elevation, m
    base: Literal["fit", "lowest"] | Annotated[float, Field(ge=-1000.0, le=10000.0)] = "fit"


class MeasureRequest(BaseModel):
    """Pixel positions of the same points in the left and right photo of a calibrated rig."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    left: list[tuple[Pixel, Pixel]] = Field(min_length=1, max_length=200)  # pixel (x, y), left photo
    right: list[tuple[Pixel, Pixel]] = Field(min_length=1, max_length=200)  # same points, right photo
    perturb_px: float = Field(0.5, gt=0.0, le=10.0)  # marking accuracy used for the uncertainty, px


class UserCreate(BaseModel):
    model_config = ConfigDict(extra="forbid")

    name: str = Field(pattern=r"^[A-Za-z0-9][A-Za-z0-9._-]{0,63}$")
    is_admin: bool = False
    label: str = Field("", max_length=200)  # what the first token is for, e.g. "field laptop"


class TokenOut(BaseModel):
    id: int
    user: str
    prefix: str  # the token's first characters, to tell tokens apart; the secret is never shown again
    label: str
    created_at: datetime
    last_used_at: datetime | None
    revoked: bool


class UserOut(BaseModel):
    name: str
    is_admin: bool
    tokens: list[TokenOut]


class TokenCreated(BaseModel):
    user: str
    token: str  # shown once: only its hash is stored


class UploadOut(BaseModel):
    """A resumable (tus) upload of one photo: how far it is, and once complete, the photo it became."""

    id: str
    url: str  # where HEAD, PATCH and DELETE go (tus's upload URL)
    filename: str
    length: int  # bytes, as Upload-Length said
    offset: int  # bytes stored so far
    complete: bool
    expires_at: datetime | None  # an unfinished upload idle until then is deleted
    image: ImageOut | None = None


class ImportCreate(BaseModel):
    """A folder to import, named relative to one of the server's import directories (``import_dirs``)."""

    model_config = ConfigDict(extra="forbid")

    root: int = Field(0, ge=0, le=1000)  # which import directory, by its place in FOTOSKHEMA_IMPORT_DIRS
    path: str = Field(".", max_length=4096)  # relative to it, with / between names; "." is the directory itself
    recursive: bool = False  # also the photos of its sub-folders

    @field_validator("path")
    @classmethod
    def _no_nul(cls, value: str) -> str:
        if "\x00" in value:
            raise ValueError("must not contain NUL characters")
        return value


class ImportOut(BaseModel):
    id: int
    flight_id: int
    root: int
    path: str
    status: str  # running, succeeded, failed, cancelled, interrupted (its API process stopped; POST it again)
    total: int  # photo files found
    done: int  # of them looked at
    imported: int  # became photos of the flight
    skipped: int  # already in the flight
    refused: int  # not photos this service takes, with why in errors
    errors: dict[str, str]  # file (relative to the folder) -> why it was refused; the first 200
    bytes_copied: int  # disk the import used: copies (a hard link uses none)
    gps: dict[str, Any]  # the folder's GPS side file as PUT /api/flights/{id}/gps answers it; {} if none
    error: str  # why the import stopped, if it did
    created_at: datetime
    updated_at: datetime
