"""Stage ``write_crack_report``: the crack survey's outputs.

Per load stage a rectified COG (a local engineering CRS in mm on the rectification plane, pixel (col, row)
centred on the plane point (col, row) * mm_per_px, so y runs down the specimen as in a plate's model frame)
and an overlay PNG, both resampled from the detection raster to the output ``mm_per_px`` (default: the
photos' own sampling); for all stages ``cracks.geojson`` (3D polylines in the specimen model's mm),
``cracks.csv`` and ``report.json``.
"""

from __future__ import annotations

import csv
import io
from typing import Any

import cv2
import numpy as np
from rasterio.windows import Window

from workers.algorithms.cracks import Crack, estimate_width, isotropic_sampling, smallest_detectable_width
from workers.algorithms.specimen import Surface, raster_shape, resample_raster
from workers.config import CrackSurveyConfig
from workers.raster_io import open_block_writer, translate_to_cog
from workers.workspace import JobWorkspace, ProgressFn, atomic_path, noop_progress

# A local engineering frame in mm (no datum on Earth): GeoTIFF keeps it as a user-defined projected CS in
# millimetres; raster Y grows down the specimen with the rows (a positive pixel height in the transform).
SPECIMEN_CRS = (
    'LOCAL_CS["specimen rectification plane (mm)",LOCAL_DATUM["specimen",32767],'
    'UNIT["millimetre",0.001],AXIS["x",EAST],AXIS["y",SOUTH]]'
)
OVERSAMPLING_WARNING = 2.0  # warn when the output raster is this many times finer than the photos' sampling
# the contrast the smallest detectable width is given at when the survey measured none (no crack wide enough
# to tell its contrast), and the contrasts it is tabled at (detection.smallest_detectable_width)
DEFAULT_CRACK_CONTRAST = 0.3
TABLED_CONTRASTS = (0.1, 0.15, 0.2, 0.25, 0.3, 0.35, 0.5)
STATUS_BGR = {"first": (0, 200, 255), "new": (0, 0, 255), "grown": (255, 0, 255), "unchanged": (0, 200, 0)}
CSV_FIELDS = (
    "stage",
    "stage_label",
    "load",
    "id",
    "length_mm",
    "mean_width_mm",
    "max_width_mm",
    "width_mm",
    "width_uncertainty_mm",
    "below_photo_resolution",
    "photo_mm_per_px",
    "orientation_deg",
    "status",
    "growth_mm",
    "x_min_mm",
    "y_min_mm",
    "x_max_mm",
    "y_max_mm",
)


def run(ws: JobWorkspace, cfg: CrackSurveyConfig, *, progress: ProgressFn = noop_progress) -> dict[str, Any]:
    """Write the rectified COGs and overlays, ``cracks.geojson``, ``cracks.csv`` and ``report.json``."""
    pairs = ws.load_comparison()
    rectified = ws.load_stage_report("rectify_specimen") or {}
    surface = ws.load_surface()
    native = rectified.get("photo_mm_per_px") or [None] * len(cfg.stages)
    output_mm = output_mm_per_px(cfg, rectified, surface.mm_per_px)
    # the specimen's extents on its plane, as rectify_specimen sized its rasters
    extent = rectified.get("extent_mm") or [(n - 1) * surface.mm_per_px for n in surface.shape[::-1]]
    stages, rows, warnings = [], [], []
    measured_contrast = (ws.load_stage_report("measure_cracks") or {}).get("crack_contrast")
    contrast = measured_contrast or DEFAULT_CRACK_CONTRAST
    for s, stage in enumerate(cfg.stages):
        progress(s / len(cfg.stages), f"load step {s + 1}/{len(cfg.stages)}")
        measured, summary = ws.load_measured_cracks(s)
        cracks = crack_rows(cfg, s, measured, pairs[s - 1]["cracks"] if s > 0 else None, native[s])
        image, mask = ws.load_rectified(s)
        shape = raster_shape(float(extent[0]), float(extent[1]), output_mm)
        image, mask = resample_raster(image, mask, surface.mm_per_px, shape, output_mm)
        _write_cog(ws, s, image, mask, cfg, output_mm)
        _write_overlay(ws, s, image, cracks, output_mm)
        warnings += _resolution_warning(stage.label, native[s], output_mm)
        stages.append(
            {
                "index": s,
                "label": stage.label,
                "load": stage.load,
                "coverage": float(mask.mean()),
                "photo_mm_per_px": native[s],
                "detection_mm_per_px": surface.mm_per_px,
                **detectability(native[s], ws.load_photo_footprint(s), contrast),
                **summary,
                "below_photo_resolution": sum(bool(c["below_photo_resolution"]) for c in cracks),
                "rectified": ws.load_step_cog_path(s).name,
                "overlay": ws.load_step_overlay_path(s).name,
                "cracks": cracks,
            }
        )
        rows += cracks
    ws.save_cracks_geojson(_geojson(rows, surface))
    _write_csv(ws, rows)
    report = {
        "kind": "crack_survey",
        "mm_per_px": output_mm,
        "detection_mm_per_px": surface.mm_per_px,
        # the coating's crack contrast the widths rest on (measure_cracks; null: no crack wide enough to tell)
        "crack_contrast": measured_contrast,
        "detectability_contrast": contrast,  # the contrast each load step's smallest detectable width is for
        "specimen": cfg.specimen.model_dump(),
        "frame": (
            "paths_mm and bbox_mm: (x, y) mm on the rectification plane, x right, y down, raster pixel "
            "(col, row) centred on (x, y) / mm_per_px; cracks.geojson: specimen model (X, Y, Z) mm"
        ),
        "plane": surface.frame.to_json(),
        "photos": ws.load_orientation(),
        "stages": stages,
        "comparisons": [{k: v for k, v in p.items() if k != "cracks"} for p in pairs],
        "warnings": warnings,
    }
    ws.save_report(report)
    progress(1.0, "report written")
    return {"stages": len(stages), "cracks": len(rows)}


def detectability(
    photo_mm: float | None, footprint: tuple[np.ndarray, float] | None, contrast: float
) -> dict[str, Any]:
    """A load step's smallest detectable crack width (mm; None: none is found reliably): at ``contrast`` and
    the photos' median sampling ``photo_mm``; its range over the specimen (the photos' local sampling,
    5th to 95th percentile over the points they see, from the ``footprint``); and at other contrasts."""
    if photo_mm is None:
        return {"smallest_detectable_width_mm": None}
    local = isotropic_sampling(footprint[0]) if footprint is not None else np.zeros(0)
    spread = np.percentile(local, [5, 95]) if len(local) else (photo_mm, photo_mm)
    return {
        "smallest_detectable_width_mm": smallest_detectable_width(photo_mm, contrast),
        "smallest_detectable_width_range_mm": [smallest_detectable_width(float(m), contrast) for m in spread],
        "detectable_width_by_contrast": [
            {"contrast": c, "width_mm": smallest_detectable_width(photo_mm, c)} for c in TABLED_CONTRASTS
        ],
    }


def _resolution_warning(label: str, native: float | None, output_mm: float) -> list[str]:
    """A warning when the output raster is much finer than the photos resolve, else none."""
    if native is None or output_mm >= native / OVERSAMPLING_WARNING:
        return []
    return [
        f"load step {label!r}: the photos resolve {native:.3g} mm per pixel on the specimen, the output "
        f"raster {output_mm:.3g}: it shows no detail finer than the photos'"
    ]


def output_mm_per_px(cfg: CrackSurveyConfig, rectified: dict[str, Any], detection_mm: float) -> float:
    """The output raster's mm per px: the option, else the photos' sampling ``rectify_specimen`` chose."""
    if cfg.mm_per_px is not None:
        return cfg.mm_per_px
    return float(rectified.get("output_mm_per_px") or detection_mm)


def crack_rows(
    cfg: CrackSurveyConfig,
    s: int,
    cracks: list[Crack],
    matches: list[dict[str, Any]] | None,
    photo_mm_per_px: float | None = None,
) -> list[dict[str, Any]]:
    """Every crack of stage ``s`` with its status against the stage before ("first" for the first stage), and
    its width as the photos resolve it (their sampling across the crack, ``Crack.photo_mm_per_px``, else the
    load step's ``photo_mm_per_px``)."""
    stage = cfg.stages[s]
    rows = []
    for k, crack in enumerate(cracks):
        match = matches[k] if matches is not None else {"status": "first", "growth_mm": None, "previous": []}
        photo_mm = crack.photo_mm_per_px or photo_mm_per_px  # across the crack where it is, else the step's
        width = estimate_width(crack.mean_width_mm, photo_mm) if photo_mm else None
        rows.append(
            {
                "stage": s,
                "stage_label": stage.label,
                "load": stage.load,
                "id": k,
                "length_mm": crack.length_mm,
                "mean_width_mm": crack.mean_width_mm,
                "max_width_mm": crack.max_width_mm,
                "width_mm": None if width is None else width.width_mm,
                "width_uncertainty_mm": None if width is None else width.uncertainty_mm,
                "below_photo_resolution": None if width is None else width.below_photo_resolution,
                "photo_mm_per_px": photo_mm,
                "orientation_deg": crack.orientation_deg,
                "status": match["status"],
                "growth_mm": match["growth_mm"],
                "previous": match["previous"],
                "bbox_mm": list(crack.bbox_mm),
                "paths_mm": [p.tolist() for p in crack.paths_mm],
            }
        )
    return rows


def _write_cog(
    ws: JobWorkspace, s: int, image: np.ndarray, mask: np.ndarray, cfg: CrackSurveyConfig, step: float
) -> None:
    tmp = ws.load_step_scratch_path(s)
    height, width = mask.shape
    with open_block_writer(tmp, width, height, SPECIMEN_CRS, [step, 0.0, -step / 2, 0.0, step, -step / 2]) as write:
        write(Window(0, 0, width, height), cv2.cvtColor(image, cv2.COLOR_BGR2RGB), mask)
    translate_to_cog(tmp, ws.load_step_cog_path(s), cfg.cog_compression)
    tmp.unlink(missing_ok=True)


def _write_overlay(ws: JobWorkspace, s: int, image: np.ndarray, cracks: list[dict[str, Any]], mm_per_px: float) -> None:
    """The rectified image with every crack drawn in its status colour."""
    overlay = image.copy()
    for crack in cracks:
        for path in crack["paths_mm"]:
            points = np.rint(np.array(path) / mm_per_px * 4).astype(np.int32).reshape(-1, 1, 2)  # 2 bits subpixel
            cv2.polylines(overlay, [points], False, STATUS_BGR[crack["status"]], 1, cv2.LINE_AA, shift=2)
    ok, png = cv2.imencode(".png", overlay)
    if not ok:
        raise RuntimeError("PNG encoding failed")
    with atomic_path(ws.load_step_overlay_path(s)) as tmp:
        tmp.write_bytes(png.tobytes())


def _geojson(rows: list[dict[str, Any]], surface: Surface) -> dict[str, Any]:
    """The cracks as 3D lines in the specimen model's own coordinates (X, Y, Z mm; Z = 0 on a plate)."""

    def lines(paths: list[list[list[float]]]) -> list[list[list[float]]]:
        return [np.round(surface.lift(np.array(p)), 4).tolist() for p in paths]

    features = [
        {
            "type": "Feature",
            "geometry": {"type": "MultiLineString", "coordinates": lines(row["paths_mm"])},
            "properties": {k: v for k, v in row.items() if k != "paths_mm"},
        }
        for row in rows
    ]
    # not geographic, so RFC 7946 has no CRS member for it: "frame" names the model's frame instead
    return {"type": "FeatureCollection", "units": "mm", "frame": "specimen model", "features": features}


def _write_csv(ws: JobWorkspace, rows: list[dict[str, Any]]) -> None:
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, CSV_FIELDS, extrasaction="ignore", lineterminator="\n")
    writer.writeheader()
    for row in rows:
        x0, y0, x1, y1 = row["bbox_mm"]
        writer.writerow({**row, "x_min_mm": x0, "y_min_mm": y0, "x_max_mm": x1, "y_max_mm": y1})
    ws.save_cracks_csv(buffer.getvalue())
