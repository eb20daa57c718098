"""The typed records of a job's internal artifacts (as OpenSfM's ``types.py`` beside ``dataset.py``).

The workspace reads and writes them (``JobWorkspace.load_x()`` / ``save_x()``); each has ``to_json`` and
``from_json`` and nothing else that touches a file. Documents a job hands to the user as they are
(``report.json``, ``calibration.json``, ``cameras.json``) stay plain JSON dicts.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np

JsonDict = dict[str, Any]


@dataclass(frozen=True)
class Frame:
    """One decoded photo of a mosaic job (``load_images``): sizes of the photo and of its working copy.

    ``gps`` is ``{"lat", "lon", "alt"}`` (degrees, metres; ``alt`` may be None) or None; ``yaw``, ``pitch``,
    ``roll`` are DJI's gimbal angles in degrees, None when the photo has none.
    """

    index: int  # position in the job's inputs; names its working copy and features
    name: str
    path: str
    orig_width: int
    orig_height: int
    width: int  # working copy, px
    height: int
    scale: float  # working copy / photo
    gps: dict[str, float | None] | None = None
    focal_length_mm: float | None = None
    focal_length_35mm: float | None = None
    yaw: float | None = None
    pitch: float | None = None
    roll: float | None = None
    relative_altitude: float | None = None
    gps_accuracy_m: float | None = None  # of ``gps``, from a GPS side file; None: the job's gps_sigma_m

    def to_json(self) -> JsonDict:
        return dataclasses.asdict(self)

    @classmethod
    def from_json(cls, data: JsonDict) -> Frame:
        return cls(**data)

    def with_size(self, width: int, height: int) -> Frame:
        """The frame as ``compose_mosaic`` sees it when orthorectification cut it to ``width`` x ``height``."""
        return dataclasses.replace(self, width=width, height=height)


@dataclass(frozen=True)
class RejectedFrame:
    """A photo left out of the mosaic, and why (in words a user can act on)."""

    index: int
    name: str
    reason: str

    def to_json(self) -> JsonDict:
        return dataclasses.asdict(self)

    @classmethod
    def from_json(cls, data: JsonDict) -> RejectedFrame:
        return cls(int(data["index"]), str(data["name"]), str(data["reason"]))


@dataclass(frozen=True)
class PairRecord:
    """A frame pair ``match_features`` tried: its matches, its model's inliers and whether it was kept.

    ``model`` is the pair's homography ``j ~ H i`` (planar mode, ``model_kind`` "H") or fundamental matrix
    (ortho mode, "F"), (3, 3), None when none was found; ``tie_points`` counts the inliers kept (accepted pairs).
    """

    i: int
    j: int
    matches: int
    inliers: int
    accepted: bool
    model_kind: Literal["H", "F"]
    model: np.ndarray | None
    tie_points: int | None = None
    # "features": descriptor matching; "guided": correlation where the other pairs' alignment predicts an
    # overlap that descriptor matching missed (:func:`workers.algorithms.mosaic.guided_tie_points`)
    found_by: Literal["features", "guided"] = "features"

    @property
    def pair(self) -> tuple[int, int]:
        return self.i, self.j

    def to_json(self) -> JsonDict:
        data: JsonDict = {
            "i": self.i,
            "j": self.j,
            "matches": self.matches,
            "inliers": self.inliers,
            "accepted": self.accepted,
            self.model_kind: None if self.model is None else self.model.tolist(),
        }
        if self.tie_points is not None:
            data["tie_points"] = self.tie_points
        if self.found_by != "features":
            data["found_by"] = self.found_by
        return data

    @classmethod
    def from_json(cls, data: JsonDict) -> PairRecord:
        kind: Literal["H", "F"] = "H" if "H" in data else "F"
        model = data[kind]
        return cls(
            int(data["i"]),
            int(data["j"]),
            int(data["matches"]),
            int(data["inliers"]),
            bool(data["accepted"]),
            kind,
            None if model is None else np.array(model, dtype=np.float64),
            data.get("tie_points"),
            "guided" if data.get("found_by") == "guided" else "features",
        )


@dataclass(frozen=True)
class PairResidual:
    """How well an accepted pair's tie points agree once every frame is in the plane, px."""

    i: int
    j: int
    rms_px: float
    max_px: float

    def to_json(self) -> JsonDict:
        return dataclasses.asdict(self)

    @classmethod
    def from_json(cls, data: JsonDict) -> PairResidual:
        return cls(int(data["i"]), int(data["j"]), float(data["rms_px"]), float(data["max_px"]))


@dataclass(frozen=True)
class DroppedPair:
    """An accepted pair the alignment left out afterwards, and why."""

    i: int
    j: int
    reason: str

    def to_json(self) -> JsonDict:
        return dataclasses.asdict(self)

    @classmethod
    def from_json(cls, data: JsonDict) -> DroppedPair:
        return cls(int(data["i"]), int(data["j"]), str(data["reason"]))


@dataclass(frozen=True)
class Alignment:
    """Every frame in one plane (``align_frames``, or ``orthorectify_frames`` in ortho mode).

    ``homographies``: frame index -> (3, 3) float64, frame px (of the image ``compose_mosaic`` warps) to
    plane px. Ortho mode also keeps the size each frame was cut to and the ground plane's height.
    """

    reference: int  # the frame whose plane the mosaic is in
    homographies: dict[int, np.ndarray]
    rejected: list[RejectedFrame]
    tie_point_rms_px: float | None
    tie_points: int
    dropped_pairs: list[DroppedPair] = field(default_factory=list)
    pair_residuals: list[PairResidual] = field(default_factory=list)
    mode: Literal["planar", "ortho"] = "planar"
    frame_sizes: dict[int, tuple[int, int]] = field(default_factory=dict)  # ortho: (width, height) as cut
    ground_z: float | None = None  # ortho: height of the ground plane, m
    # strips with GPS: frame -> its least well known corner's standard error, plane px (alignment.corner_sigmas)
    corner_sigma_px: dict[int, float] = field(default_factory=dict)

    def to_json(self) -> JsonDict:
        return {
            "mode": self.mode,
            "reference": self.reference,
            "homographies": {str(k): H.tolist() for k, H in sorted(self.homographies.items())},
            "rejected": [r.to_json() for r in self.rejected],
            "tie_point_rms_px": self.tie_point_rms_px,
            "tie_points": self.tie_points,
            "dropped_pairs": [p.to_json() for p in self.dropped_pairs],
            "pairs": [p.to_json() for p in self.pair_residuals],
            "frame_sizes": {str(k): list(s) for k, s in sorted(self.frame_sizes.items())},
            "ground_z": self.ground_z,
            "corner_sigma_px": {str(k): v for k, v in sorted(self.corner_sigma_px.items())},
        }

    @classmethod
    def from_json(cls, data: JsonDict) -> Alignment:
        return cls(
            reference=int(data["reference"]),
            homographies={int(k): np.array(H, dtype=np.float64) for k, H in data["homographies"].items()},
            rejected=[RejectedFrame.from_json(r) for r in data["rejected"]],
            tie_point_rms_px=data["tie_point_rms_px"],
            tie_points=int(data["tie_points"]),
            dropped_pairs=[DroppedPair.from_json(p) for p in data.get("dropped_pairs", [])],
            pair_residuals=[PairResidual.from_json(p) for p in data.get("pairs", [])],
            mode=data.get("mode", "planar"),
            frame_sizes={int(k): (int(w), int(h)) for k, (w, h) in data.get("frame_sizes", {}).items()},
            ground_z=data.get("ground_z"),
            corner_sigma_px={int(k): float(v) for k, v in data.get("corner_sigma_px", {}).items()},
        )


@dataclass(frozen=True)
class Georef:
    """The mosaic's output grid (``georeference``, or ``orthorectify_frames``): its size, how an output pixel
    maps to the mosaic plane and, when georeferenced, to a projected CRS.

    ``output_to_plane`` and ``plane_to_map`` are (3, 3) float64; ``transform`` is the GDAL-style affine
    ``(a, b, c, d, e, f)`` from output pixel to map (identity when not georeferenced).
    """

    georeferenced: bool
    reason: str  # why not georeferenced ("" when it is)
    epsg: int | None
    plane_to_map: np.ndarray
    gsd_m: float | None  # the mosaic's pixel size on the ground
    width: int
    height: int
    transform: list[float]
    output_to_plane: np.ndarray
    gps_frames: int | None = None
    gps_residual_rms_m: float | None = None
    gps_residuals_m: dict[str, float] = field(default_factory=dict)  # by frame name
    gps_drift_m: float | None = None  # largest mean miss over a tenth of the route (georeference.gps_drift_m)
    output_scale: float = 1.0  # output px per plane px (the plane has the reference working copy's px)

    def to_json(self) -> JsonDict:
        return {
            "georeferenced": self.georeferenced,
            "reason": self.reason,
            "epsg": self.epsg,
            "plane_to_map": self.plane_to_map.tolist(),
            "gsd_m": self.gsd_m,
            "width": self.width,
            "height": self.height,
            "transform": list(self.transform),
            "output_to_plane": self.output_to_plane.tolist(),
            "gps_frames": self.gps_frames,
            "gps_residual_rms_m": self.gps_residual_rms_m,
            "gps_residuals_m": dict(self.gps_residuals_m),
            "gps_drift_m": self.gps_drift_m,
            "output_scale": self.output_scale,
        }

    @classmethod
    def from_json(cls, data: JsonDict) -> Georef:
        return cls(
            georeferenced=bool(data["georeferenced"]),
            reason=str(data["reason"]),
            epsg=data["epsg"],
            plane_to_map=np.array(data["plane_to_map"], dtype=np.float64),
            gsd_m=data["gsd_m"],
            width=int(data["width"]),
            height=int(data["height"]),
            transform=[float(v) for v in data["transform"]],
            output_to_plane=np.array(data["output_to_plane"], dtype=np.float64),
            gps_frames=data.get("gps_frames"),
            gps_residual_rms_m=data.get("gps_residual_rms_m"),
            gps_residuals_m=dict(data.get("gps_residuals_m", {})),
            gps_drift_m=data.get("gps_drift_m"),
            output_scale=float(data.get("output_scale", 1.0)),
        )


@dataclass(frozen=True)
class Coverage:
    """What the mosaic covers (``compose_mosaic``): outline rings (N, 2) in output px, and the share of the grid."""

    outline_px: list[np.ndarray]
    area_fraction: float

    def to_json(self) -> JsonDict:
        return {"outline_px": [ring.tolist() for ring in self.outline_px], "area_fraction": self.area_fraction}

    @classmethod
    def from_json(cls, data: JsonDict) -> Coverage:
        return cls(
            [np.array(ring, dtype=np.float64).reshape(-1, 2) for ring in data["outline_px"]],
            float(data["area_fraction"]),
        )
