"""Stage ``rectify_specimen``: every load stage's photos rendered orthographically onto the specimen's plane
(a plate, or a mesh's best-fit or chosen plane with its heights and occlusions)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from workers.algorithms.specimen import (
    Mesh,
    PlaneFrame,
    Surface,
    best_fit_plane,
    compose_views,
    mesh_surface,
    photo_footprint,
    photo_sampling,
    plane_through,
    plate_surface,
    pose_from_json,
    raster_shape,
    read_mesh,
)
from workers.config import CrackSurveyConfig
from workers.pipeline import PipelineError, option_camera
from workers.workspace import JobWorkspace, ProgressFn, noop_progress

MAX_RASTER_PIXELS = 200_000_000  # a larger raster is refused before anything is allocated (~26 B/px held)
COARSE_PX = 400  # pixels along the specimen's longer side of the raster its photo sampling is measured on


def run(ws: JobWorkspace, cfg: CrackSurveyConfig, *, progress: ProgressFn = noop_progress) -> dict[str, Any]:
    """Write the surface (``rectified/surface.npz``) and per load stage ``rectified/stage_NN.npz``:
    (H, W, 3) BGR image and the mask its photos see, on the detection raster: ``detection_oversampling``
    times finer than the photos' own sampling on the specimen, whatever the output ``mm_per_px``; and the
    photos' pixel footprint on a coarse raster (``specimen.photo_footprint``)."""
    camera = option_camera(cfg.camera, "camera")
    poses = {p["image"]: pose_from_json(p) for p in ws.load_orientation()}
    paths = {f["name"]: f["path"] for f in ws.load_inputs()}
    shape = specimen_shape(ws, cfg, np.mean([C for _, C in poses.values()], axis=0))
    coarse = shape.surface(max(shape.width_mm, shape.height_mm) / COARSE_PX)
    sampling = [photo_sampling(camera, [poses[p.image] for p in stage.photos], coarse) for stage in cfg.stages]
    for stage, mm in zip(cfg.stages, sampling, strict=True):
        if not np.isfinite(mm):
            raise PipelineError(
                f"load step {stage.label!r}: its photos see no part of the specimen; "
                "check the control points' model coordinates"
            )
    detection_mm = round(min(sampling) / cfg.detection_oversampling, 4)
    _check_size(shape.width_mm, shape.height_mm, detection_mm, "the photos' sampling")
    output_mm = cfg.mm_per_px if cfg.mm_per_px is not None else round(min(sampling), 4)
    _check_size(shape.width_mm, shape.height_mm, output_mm, "mm_per_px")
    surface = shape.surface(detection_mm)
    ws.save_surface(surface)
    coverage: list[float] = []
    photo_mm_per_px: list[float] = []
    for s, stage in enumerate(cfg.stages):
        progress(s / len(cfg.stages), f"load step {s + 1}/{len(cfg.stages)}")
        views = [(_read(paths[p.image]), *poses[p.image]) for p in stage.photos]
        image, mask, density = compose_views(camera, views, surface, cfg.compose)
        # how far a photo pixel reaches across a crack at each point, for its width (measure_cracks)
        footprint = photo_footprint(camera, [poses[p.image] for p in stage.photos], coarse)
        ws.save_rectified(s, image, mask, (footprint, coarse.mm_per_px))
        coverage.append(round(float(mask.mean()), 4))
        # the photos' own sampling on the specimen as composed (the finest photo at each point)
        photo_mm_per_px.append(round(float(np.median(1.0 / np.sqrt(density[mask]))), 4))
    progress(1.0, f"{len(cfg.stages)} load step(s) rectified")
    return {
        "stages": len(cfg.stages),
        "width_px": surface.shape[1],
        "height_px": surface.shape[0],
        "coverage": coverage,
        "photo_mm_per_px": photo_mm_per_px,
        "detection_mm_per_px": detection_mm,
        "output_mm_per_px": output_mm,
        "extent_mm": [shape.width_mm, shape.height_mm],
        "plane": surface.frame.to_json(),
    }


@dataclass(frozen=True)
class SpecimenShape:
    """The specimen before it is rasterised: a plate's size, or a mesh and its plane."""

    width_mm: float
    height_mm: float
    mesh: Mesh | None = None
    frame: PlaneFrame | None = None
    camera_side: np.ndarray | None = None

    def surface(self, mm_per_px: float) -> Surface:
        """The plate, or the mesh rasterised onto its plane, at ``mm_per_px``."""
        if self.mesh is None or self.frame is None or self.camera_side is None:
            return plate_surface(self.width_mm, self.height_mm, mm_per_px)
        return mesh_surface(self.mesh, self.frame, mm_per_px, self.camera_side)


def specimen_shape(ws: JobWorkspace, cfg: CrackSurveyConfig, camera_side: np.ndarray) -> SpecimenShape:
    """The plate, or the mesh with its chosen or best-fit plane (rasterised later on the cameras' side)."""
    specimen = cfg.specimen
    if specimen.mesh is None:
        assert specimen.width_mm is not None and specimen.height_mm is not None  # the config's validator
        return SpecimenShape(specimen.width_mm, specimen.height_mm)
    try:
        mesh = read_mesh(ws.specimen_model_file(specimen.mesh).read_bytes(), specimen.mesh)
        frame = best_fit_plane(mesh) if specimen.plane is None else plane_through(mesh, np.array(specimen.plane))
    except (OSError, ValueError) as exc:
        raise PipelineError(f"specimen model: {exc}") from None
    extent = frame.to_plane(mesh.vertices).max(axis=0)
    return SpecimenShape(float(extent[0]), float(extent[1]), mesh, frame, camera_side)


def _check_size(width_mm: float, height_mm: float, mm_per_px: float, what: str) -> None:
    rows, cols = raster_shape(width_mm, height_mm, mm_per_px)
    if rows * cols > MAX_RASTER_PIXELS:
        raise PipelineError(
            f"the specimen is {cols} x {rows} px at {mm_per_px} mm/px ({what}), more than "
            f"{MAX_RASTER_PIXELS} px; choose a coarser mm_per_px or photos that resolve less of it"
        )


def _read(path: str) -> np.ndarray:
    image = cv2.imread(path, cv2.IMREAD_COLOR)
    if image is None:
        raise PipelineError(f"{Path(path).name}: the photo could not be decoded")
    return image
