"""Crack-survey rectification against OpenCV, and the time of detection and measurement per megapixel.

Run by hand from the repository root (never in CI)::

    .venv/bin/python bench/crack_survey.py [--mm-per-px 0.1] [--json OUT]

Scenes (``tests/crack_scenes.py``, written to a temporary folder): a 400 x 300 mm plate and a curved panel
(arc 400 mm, radius 300 mm, as a mesh of 8192 triangles), each photographed at 45 degrees by a
2008 x 1336 camera with Brown distortion (the UAV frame size of our source documents).

- **Rectification** of one photo onto the specimen raster at ``--mm-per-px``:
  ours (``specimen.compose_views``, as ``rectify_specimen`` runs it: per raster pixel the full camera
  model, occlusion z-buffer for the mesh, Lanczos resampling, in row blocks) against OpenCV's way for a
  plate, ``cv2.undistort`` then ``cv2.warpPerspective`` with the plane's homography (Lanczos too). OpenCV has
  no mesh rectification, so the panel row has no reference. The mean absolute grey difference between the
  two plate rasters tells that they render the same thing.
- **Detection and measurement**: the service's tiled detector (``cracks.detect_cracks``) and
  ``measure_cracks`` on the rectified plate, seconds per raster megapixel and peak memory (no reference:
  OpenCV has no crack detector).

Every run is in its own spawned child (peak RSS = that run's VmHWM). Ratios are ours / OpenCV.

``--hairlines``: instead, whole surveys (every stage, ``tests.crack_scenes.run_survey``) of hairline plates
(800 x 600 photos, cracks of 0.5-3 photo px in turn, 30 % contrast, 0.5 px PSF, seeds ``--seeds``, one view
at each of 30, 45 and 60 degrees) at ``mm_per_px`` 0.5x, 1x and 2x the photos' sampling: recall per width
class (a crack is found when 80 % of its centreline lies within max(1 mm, 2 photo px) of a reported crack),
total-length error of the cracks found, false length, and width error (estimate - truth) per class.
``--widths-px`` and ``--ratios`` choose other width classes and output rasters; a summary of the width errors
of the cracks not flagged below photo resolution closes the run.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.mosaic_vs_opencv import in_child, peak_rss_mib  # noqa: E402

FRAME = (2008, 1336)


def make_scene(folder: str, radius_mm: float | None) -> dict[str, Any]:
    """Render the scene once; what the children need, as plain data."""
    from tests.crack_scenes import make_crack_survey

    scene = make_crack_survey(
        Path(folder),
        [(45.0, 0.0)],
        seed=3,
        width_mm=400.0,
        height_mm=300.0,
        frame_size=FRAME,
        panel_radius_mm=radius_mm,
    )
    photo = scene.photos[0]
    return {
        "camera": scene.camera.to_json(),
        "photo": str(photo.path),
        "R": photo.R.tolist(),
        "C": photo.C.tolist(),
        "mesh": str(scene.mesh_path) if scene.mesh_path else None,
        "width_mm": 400.0,
        "height_mm": 300.0,
    }


def _surface(scene: dict[str, Any], mm_per_px: float, C: Any) -> Any:
    from workers.algorithms.specimen import best_fit_plane, mesh_surface, plate_surface, read_mesh

    if scene["mesh"] is None:
        return plate_surface(scene["width_mm"], scene["height_mm"], mm_per_px)
    mesh = read_mesh(Path(scene["mesh"]).read_bytes(), scene["mesh"])
    return mesh_surface(mesh, best_fit_plane(mesh), mm_per_px, C)


def run_ours(scene: dict[str, Any], mm_per_px: float, out: str) -> dict[str, Any]:
    import cv2
    import numpy as np

    from workers.algorithms.geometry import Camera
    from workers.algorithms.specimen import compose_views

    camera = Camera.from_json(scene["camera"])
    image = cv2.imread(scene["photo"], cv2.IMREAD_COLOR)
    R, C = np.array(scene["R"]), np.array(scene["C"])
    started = time.perf_counter()
    surface = _surface(scene, mm_per_px, C)
    raster, mask, _ = compose_views(camera, [(image, R, C)], surface, "best")
    seconds = time.perf_counter() - started
    np.save(out, raster)
    return {
        "ok": True,
        "seconds": seconds,
        "peak_mib": peak_rss_mib(),
        "size": list(raster.shape[1::-1]),
        "coverage": float(mask.mean()),
    }


def run_opencv(scene: dict[str, Any], mm_per_px: float, out: str) -> dict[str, Any]:
    import cv2
    import numpy as np

    from workers.algorithms.geometry import Camera

    camera = Camera.from_json(scene["camera"])
    image = cv2.imread(scene["photo"], cv2.IMREAD_COLOR)
    R, C = np.array(scene["R"]), np.array(scene["C"])
    K = np.array([[camera.fx, 0, camera.cx], [0, camera.fy, camera.cy], [0, 0, 1]])
    dist = np.array([camera.k1, camera.k2, camera.t1, camera.t2, camera.k3])
    t = -R @ C
    plane_to_photo = K @ np.column_stack([R[:, 0], R[:, 1], t]) @ np.diag([mm_per_px, mm_per_px, 1.0])
    cols = int(np.floor(scene["width_mm"] / mm_per_px + 1e-9)) + 1
    rows = int(np.floor(scene["height_mm"] / mm_per_px + 1e-9)) + 1
    started = time.perf_counter()
    ideal = cv2.undistort(image, K, dist)
    raster = cv2.warpPerspective(ideal, plane_to_photo, (cols, rows), flags=cv2.INTER_LANCZOS4 | cv2.WARP_INVERSE_MAP)
    seconds = time.perf_counter() - started
    np.save(out, raster)
    return {"ok": True, "seconds": seconds, "peak_mib": peak_rss_mib(), "size": [cols, rows]}


def run_detection(raster_file: str, mm_per_px: float) -> dict[str, Any]:
    import numpy as np

    from workers.algorithms.cracks import background_px, detect_cracks, load_crack_model, measure_cracks
    from workers.config import CrackSurveyConfig

    raster = np.load(raster_file)
    model = load_crack_model()
    min_contrast = CrackSurveyConfig.model_fields["min_crack_contrast"].default
    started = time.perf_counter()
    mask = detect_cracks(raster, model=model, min_contrast=min_contrast, background_px=background_px(mm_per_px))
    detected = time.perf_counter()
    cracks = measure_cracks(mask, mm_per_px, min_length_mm=1.0)
    measured = time.perf_counter()
    mpx = raster.shape[0] * raster.shape[1] / 1e6
    return {
        "ok": True,
        "megapixels": mpx,
        "detect_s_per_mpx": (detected - started) / mpx,
        "measure_s_per_mpx": (measured - detected) / mpx,
        "cracks": len(cracks),
        "peak_mib": peak_rss_mib(),
    }


HAIRLINE_WIDTHS_PX = (0.5, 0.75, 1.0, 1.5, 2.0, 3.0)
CONTRAST_WIDTHS_PX = (0.75, 1.0, 1.5, 2.0, 3.0, 4.0, 6.0)


def run_hairlines(
    seeds: list[int],
    angles: tuple[float, ...] = (30.0, 45.0, 60.0),
    widths_px: tuple[float, ...] = HAIRLINE_WIDTHS_PX,
    ratios: tuple[float, ...] = (0.5, 1.0, 2.0),
) -> list[dict[str, Any]]:
    """One row per (seed, angle, ratio): recall per width class, length, false length and width errors."""
    import numpy as np

    from tests.crack_scenes import make_crack_survey, rows_along, run_survey, score_stage

    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for seed in seeds:
            for angle in angles:
                scene = make_crack_survey(
                    Path(tmp) / f"s{seed}_{angle:.0f}" / "photos",
                    [(angle, 15.0)],
                    seed=seed,
                    frame_size=(800, 600),
                    widths_px=widths_px,
                    contrast=0.3,
                    blur_px=0.5,
                )
                p = scene.photo_mm_per_px
                for ratio in ratios:
                    started = time.perf_counter()
                    report = run_survey(
                        scene, Path(tmp) / f"s{seed}_{angle:.0f}" / f"x{ratio}", scene.options(round(ratio * p, 4))
                    )
                    found: dict[float, list[bool]] = {}
                    width_errors: dict[float, list[tuple[float, float, bool]]] = {}
                    false_mm = true_mm = found_true = found_reported = 0.0
                    for stage, truth in zip(report["stages"], scene.stages, strict=True):
                        score = score_stage(stage, truth, max(1.0, 2 * p))
                        false_mm += score.false_mm
                        true_mm += score.true_mm
                        for crack, share in zip(truth, score.found, strict=True):
                            w = round(crack.width_mm / p, 2)
                            found.setdefault(w, []).append(share > 0.8)
                            if share > 0.8:
                                found_true += crack.length_mm
                        for crack, share, row in zip(
                            truth, score.found, rows_along(stage, truth, max(1.0, 2 * p)), strict=True
                        ):
                            if share > 0.8 and row is not None:
                                found_reported += row["length_mm"]
                                width_errors.setdefault(round(crack.width_mm / p, 2), []).append(
                                    (
                                        row["width_mm"] - crack.width_mm,
                                        row["width_uncertainty_mm"],
                                        row["below_photo_resolution"],
                                    )
                                )
                    rows.append(
                        {
                            "seed": seed,
                            "angle": angle,
                            "ratio": ratio,
                            "photo_mm_per_px": p,
                            "detection_mm_per_px": report["detection_mm_per_px"],
                            "recall": {w: float(np.mean(v)) for w, v in sorted(found.items())},
                            "length_error": found_reported / max(found_true, 1e-9) - 1,
                            "false_share": false_mm / true_mm,
                            "width_error_mm": {w: [round(e[0], 3) for e in v] for w, v in sorted(width_errors.items())},
                            "flagged": {w: [bool(e[2]) for e in v] for w, v in sorted(width_errors.items())},
                            "seconds": round(time.perf_counter() - started, 1),
                        }
                    )
                    print(json.dumps(rows[-1]), flush=True)
    return rows


def run_contrasts(
    seeds: list[int], angles: list[float], contrasts: list[float], widths_px: tuple[float, ...]
) -> list[dict[str, Any]]:
    """Recall against the smallest detectable width the report claims: hairline plates (800 x 600 photos, 0.5
    px PSF) per seed, angle and contrast, surveyed at the default raster; per true crack, its width in photo
    px (the true camera's isotropic sampling where it is), whether it was found, and whether the claim
    (``detection.smallest_detectable_width`` at the true contrast and that sampling) says it is found."""
    from tests.crack_scenes import crack_sampling, make_crack_survey, run_survey, score_stage
    from workers.algorithms.cracks import smallest_detectable_width

    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for seed in seeds:
            for angle in angles:
                for contrast in contrasts:
                    folder = Path(tmp) / f"s{seed}_{angle:.0f}_{contrast}"
                    scene = make_crack_survey(
                        folder / "photos",
                        [(angle, 15.0)],
                        seed=seed,
                        frame_size=(800, 600),
                        widths_px=widths_px,
                        contrast=contrast,
                        blur_px=0.5,
                    )
                    options = scene.options(0.0)
                    del options["mm_per_px"]
                    report = run_survey(scene, folder / "survey", options)
                    tolerance = max(1.0, 2 * scene.photo_mm_per_px)
                    for s, (stage, truth) in enumerate(zip(report["stages"], scene.stages, strict=True)):
                        score = score_stage(stage, truth, tolerance)
                        for crack, found in zip(truth, score.found, strict=True):
                            iso, _ = crack_sampling(scene, crack, s)
                            claimed = smallest_detectable_width(iso, contrast)
                            row = {
                                "seed": seed,
                                "angle": angle,
                                "contrast": contrast,
                                "width_px": round(crack.width_mm / scene.photo_mm_per_px, 2),
                                "local_px": crack.width_mm / iso,
                                "found": found > 0.8,
                                "claimed": claimed is not None and crack.width_mm >= claimed,
                                "false_share": score.false_mm / score.true_mm,
                            }
                            rows.append(row)
                    print(json.dumps(rows[-1]), flush=True)
    return rows


def print_contrasts(rows: list[dict[str, Any]]) -> None:
    """Per angle and contrast: recall per width class (nominal photo px) and how the claim held."""
    from workers.algorithms.cracks import smallest_detectable_width

    widths = sorted({r["width_px"] for r in rows})
    print("\nrecall per width class (photo px): found/true; claim: cracks at least the smallest detectable width")
    print(
        f"{'deg':>3} {'contrast':>8} | "
        + " ".join(f"{w:>5.2f}" for w in widths)
        + " | claimed px  found  narrower found"
    )
    for angle in sorted({r["angle"] for r in rows}):
        for contrast in sorted({r["contrast"] for r in rows}):
            group = [r for r in rows if r["angle"] == angle and r["contrast"] == contrast]
            cells = []
            for w in widths:
                cls = [r["found"] for r in group if r["width_px"] == w]
                cells.append(f"{sum(cls)}/{len(cls)}" if cls else "-")
            claimed = [r["found"] for r in group if r["claimed"]]
            narrower = [r["found"] for r in group if not r["claimed"]]
            w_min = smallest_detectable_width(1.0, contrast)
            claim = "none" if w_min is None else f"{w_min:.2f}"
            print(
                f"{angle:>3.0f} {contrast:>8.2f} | "
                + " ".join(f"{c:>5}" for c in cells)
                + f" | {claim:>10} {sum(claimed):>2}/{len(claimed):<2}"
                f" {sum(narrower):>5}/{len(narrower)}"
            )
    claimed = [r["found"] for r in rows if r["claimed"]]
    print(f"all: {sum(claimed)} of {len(claimed)} cracks at least the claimed width found")


def print_width_errors(rows: list[dict[str, Any]]) -> None:
    """Per angle and width class (photo px), the mean and worst width error (mm) of the unflagged cracks."""
    import numpy as np

    for angle in sorted({r["angle"] for r in rows}):
        classes = sorted({w for r in rows if r["angle"] == angle for w in r["width_error_mm"]})
        for w in classes:
            errors = [
                e
                for r in rows
                if r["angle"] == angle
                for e, flagged in zip(r["width_error_mm"].get(w, []), r["flagged"].get(w, []), strict=True)
                if not flagged
            ]
            flagged = sum(f for r in rows if r["angle"] == angle for f in r["flagged"].get(w, []))
            if errors:
                print(
                    f"{angle:4.0f} deg, {w:4.2f} photo px: {len(errors):3d} measured, width error mean "
                    f"{np.mean(errors):+.3f} mm, worst {max(errors, key=abs):+.3f} mm ({flagged} flagged)"
                )
            else:
                print(f"{angle:4.0f} deg, {w:4.2f} photo px: all {flagged} flagged below photo resolution")


ISSUE_WIDTHS_MM = (0.10, 0.15, 0.20, 0.25, 0.30)


def issue_scene(folder: Path, angle: float, seed: int, frame: tuple[int, int]) -> Any:
    """The plate of issue 13: 300 x 200 mm, photos of ``frame`` px (4000 x 3000) with Brown distortion from
    ``angle`` degrees (0.11-0.16 mm per photo pixel at 4000 x 3000), 8 cracks of 18-60 mm at load step 1 (one
    grows 15 mm and 2 are new at load step 2), 0.10-0.30 mm wide in turn, 35 % darker than the coating,
    through a 0.5 px PSF, on grain under uneven light."""
    from tests.crack_scenes import make_crack_survey

    return make_crack_survey(
        folder,
        [(angle, 15.0)],
        seed=seed,
        width_mm=300.0,
        height_mm=200.0,
        frame_size=frame,
        widths_mm=ISSUE_WIDTHS_MM,
        contrast=0.35,
        blur_px=0.5,
        cracks=(8, 2),
        lengths_mm=(18.0, 60.0),
    )


def score_survey(scene: Any, report: dict[str, Any]) -> dict[str, Any]:
    """A survey's ``report.json`` against its scene's true cracks: recall per width class (mm; a crack is found
    when 80 % of its centreline lies within max(1 mm, 2 photo px) of a reported crack), total-length error,
    false length, and the width errors of the cracks found, apart for those at least 2 photo px wide across
    (the true camera's pixel across each crack) and those narrower (with their flags and intervals)."""
    from tests.crack_scenes import photo_px_across, rows_along, score_stage

    tolerance = max(1.0, 2 * scene.photo_mm_per_px)
    found: dict[float, list[bool]] = {}
    wide: list[float] = []
    narrow: list[tuple[float, bool, bool]] = []  # error, flagged, truth within the stated interval
    true_mm = reported_mm = false_mm = 0.0
    detectable_true = detectable_reported = 0.0  # cracks at least the width the report says it finds
    for s, (stage, truth) in enumerate(zip(report["stages"], scene.stages, strict=True)):
        score = score_stage(stage, truth, tolerance)
        true_mm += score.true_mm
        reported_mm += stage["total_length_mm"]
        false_mm += score.false_mm
        smallest = stage["smallest_detectable_width_mm"] or float("inf")
        for crack, share, row in zip(truth, score.found, rows_along(stage, truth, tolerance), strict=True):
            found.setdefault(round(crack.width_mm, 3), []).append(share > 0.8)
            if crack.width_mm >= smallest:
                detectable_true += crack.length_mm
                detectable_reported += row["length_mm"] if row is not None else 0.0
            if share <= 0.8 or row is None:
                continue
            error = row["width_mm"] - crack.width_mm
            if crack.width_mm >= 2 * photo_px_across(scene, crack, s):
                wide.append(error)
            else:
                inside = abs(error) <= row["width_uncertainty_mm"] + 1e-9
                narrow.append((error, bool(row["below_photo_resolution"]), inside))
    return {
        "recall": {w: f"{sum(v)}/{len(v)}" for w, v in sorted(found.items())},
        "length_error": reported_mm / true_mm - 1,
        # the cracks at least as wide as the report's smallest detectable width: their reported lengths
        "length_error_detectable": detectable_reported / detectable_true - 1 if detectable_true else None,
        "false_share": false_mm / true_mm,
        "width_error_2px": wide,
        "width_error_narrow": narrow,
    }


def run_done_when(seeds: list[int], angles: list[float], ratios: list[float], frame: tuple[int, int]) -> list[dict]:
    """Issue 13's "Done when" table: the issue's plate per seed and angle, surveyed through ``workers.pipeline``
    (every stage of a ``crack_survey`` job, as the worker runs them) first with the default ``mm_per_px`` (the
    photos' own sampling: 1x), then at each ``ratios`` times it."""
    from tests.crack_scenes import run_survey

    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for seed in seeds:
            for angle in angles:
                started = time.perf_counter()
                scene = issue_scene(Path(tmp) / f"s{seed}_{angle:.0f}" / "photos", angle, seed, frame)
                rendered = time.perf_counter() - started
                native = None
                for ratio in sorted(ratios, key=lambda r: r != 1.0):  # 1x, the default, first
                    options = scene.options(0.0)
                    if ratio == 1.0:
                        del options["mm_per_px"]
                    else:
                        options["mm_per_px"] = round(ratio * native, 4)
                    root = Path(tmp) / f"s{seed}_{angle:.0f}" / f"x{ratio}"
                    started = time.perf_counter()
                    report = run_survey(scene, root, options)
                    seconds = time.perf_counter() - started
                    native = native or report["mm_per_px"]
                    stage_seconds = {
                        name: json.loads(f.read_text())["wall_seconds"] for name, f in _stage_reports(root).items()
                    }
                    row = {
                        "seed": seed,
                        "angle": angle,
                        "ratio": ratio,
                        "mm_per_px": report["mm_per_px"],
                        "photo_mm_per_px": [st["photo_mm_per_px"] for st in report["stages"]],
                        "detection_mm_per_px": report["detection_mm_per_px"],
                        "smallest_detectable_width_mm": [st["smallest_detectable_width_mm"] for st in report["stages"]],
                        "counts": [st["count"] for st in report["stages"]],
                        "true_counts": [len(t) for t in scene.stages],
                        **score_survey(scene, report),
                        "render_s": round(rendered, 1),
                        "survey_s": round(seconds, 1),
                        "stage_s": stage_seconds,
                        "detection_megapixels": _raster_megapixels(root) * len(scene.stages),
                    }
                    rows.append(row)
                    print(json.dumps(row), flush=True)
    return rows


def _stage_reports(root: Path) -> dict[str, Path]:
    return {f.stem: f for f in sorted((root / "reports").glob("*.json"))}


def _raster_megapixels(root: Path) -> float:
    import numpy as np

    with np.load(root / "rectified" / "surface.npz") as data:
        return float(data["height"].size) / 1e6


def _percent(share: float | None) -> str:
    return "-" if share is None else f"{100 * share:+.1f}%"


def print_done_when(rows: list[dict]) -> None:
    """The table of issue 13's "Done when": per angle and output raster, recall per width class, total-length
    error, false length, width errors, and the time it took."""
    import numpy as np

    classes = sorted({w for r in rows for w in r["recall"]})
    head = " ".join(f"{w:>5.2f}" for w in classes)
    print(
        "\nrecall per width class (mm): found/true over both load steps; length: total reported against total true,"
        " '>=min' for the cracks at least the smallest detectable width the report gives; widths: estimate - truth, mm"
    )
    print(
        f"{'seed':>4} {'deg':>3} {'ratio':>5} {'mm/px':>6} {'photo':>11} | {head} | {'length':>7} {'>=min':>6} "
        f"{'false':>6} | "
        f"{'>=2 px: n  mean  worst':>22} | {'<2 px: n flag in  worst':>23} | {'s':>5}"
    )
    for r in rows:
        wide, narrow = r["width_error_2px"], r["width_error_narrow"]
        wide_text = f"{len(wide):>2} {np.mean(wide):+.3f} {max(wide, key=abs):+.3f}" if wide else f"{0:>2}"
        narrow_text = (
            f"{len(narrow):>2} {sum(f for _, f, _ in narrow):>4} {sum(i for _, _, i in narrow):>2} "
            f"{max((e for e, _, _ in narrow), key=abs):+.3f}"
            if narrow
            else f"{0:>2}"
        )
        photo = "-".join(f"{p:.3f}" for p in sorted({min(r["photo_mm_per_px"]), max(r["photo_mm_per_px"])}))
        print(
            f"{r['seed']:>4} {r['angle']:>3.0f} {r['ratio']:>5.1f} {r['mm_per_px']:>6.4f} {photo:>11} | "
            + " ".join(f"{r['recall'].get(w, '-'):>5}" for w in classes)
            + f" | {100 * r['length_error']:>+6.1f}% {_percent(r['length_error_detectable']):>6} "
            f"{100 * r['false_share']:>5.1f}% | {wide_text:>22} | "
            f"{narrow_text:>23} | {r['survey_s']:>5.0f}"
        )
    wide = [e for r in rows for e in r["width_error_2px"]]
    narrow = [n for r in rows for n in r["width_error_narrow"]]
    if wide:
        worst = max(wide, key=abs)
        print(f"cracks >= 2 photo px across: {len(wide)} measured, mean {np.mean(wide):+.3f} mm, worst {worst:+.3f} mm")
    if narrow:
        flagged, inside = sum(f for _, f, _ in narrow), sum(i for _, _, i in narrow)
        worst = max((e for e, _, _ in narrow), key=abs)
        print(
            f"cracks < 2 photo px across: {len(narrow)} measured, {flagged} flagged below photo resolution, truth "
            f"within the stated interval for {inside}, worst {worst:+.3f} mm"
        )
    for r in rows:
        detect = r["stage_s"].get("detect_cracks")
        if detect:
            print(
                f"seed {r['seed']} {r['angle']:.0f} deg x{r['ratio']}: survey {r['survey_s']:.0f} s, detection "
                f"{detect / r['detection_megapixels']:.1f} s per raster MPx ({r['detection_megapixels']:.1f} MPx), "
                f"stages {json.dumps(r['stage_s'])}"
            )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--mm-per-px", type=float, default=0.1)
    parser.add_argument("--json", type=Path, help="also write the figures here")
    parser.add_argument("--hairlines", action="store_true", help="hairline recall and widths at 0.5x/1x/2x")
    parser.add_argument("--seeds", type=int, nargs="+", default=[31])
    parser.add_argument("--widths-px", type=float, nargs="+", default=list(HAIRLINE_WIDTHS_PX))
    parser.add_argument("--ratios", type=float, nargs="+", default=[0.5, 1.0, 2.0])
    parser.add_argument("--done-when", action="store_true", help="issue 13's plate at 30/45/60 deg, 0.5x/1x/2x")
    parser.add_argument("--contrasts", type=float, nargs="+", help="recall against the smallest detectable width")
    parser.add_argument("--angles", type=float, nargs="+", default=[30.0, 45.0, 60.0])
    parser.add_argument("--frame", type=int, nargs=2, default=[4000, 3000], metavar=("W", "H"))
    args = parser.parse_args(argv)
    import numpy as np

    if args.contrasts:
        seeds = args.seeds if args.seeds != [31] else [29, 37]
        widths = tuple(args.widths_px) if args.widths_px != list(HAIRLINE_WIDTHS_PX) else CONTRAST_WIDTHS_PX
        recall = run_contrasts(seeds, args.angles, args.contrasts, widths)
        print_contrasts(recall)
        if args.json:
            args.json.write_text(json.dumps(recall, indent=2))
        return 0
    if args.done_when:
        seeds = args.seeds if args.seeds != [31] else [202]
        done = run_done_when(seeds, args.angles, args.ratios, (args.frame[0], args.frame[1]))
        print_done_when(done)
        if args.json:
            args.json.write_text(json.dumps(done, indent=2))
        return 0

    if args.hairlines:
        rows = run_hairlines(args.seeds, widths_px=tuple(args.widths_px), ratios=tuple(args.ratios))
        print_width_errors(rows)
        if args.json:
            args.json.write_text(json.dumps(rows, indent=2))
        return 0

    results: dict[str, Any] = {}
    with tempfile.TemporaryDirectory() as tmp:
        plate = make_scene(str(Path(tmp) / "plate"), None)
        panel = make_scene(str(Path(tmp) / "panel"), 300.0)
        ours_file, cv_file, panel_file = (str(Path(tmp) / n) for n in ("ours.npy", "cv.npy", "panel.npy"))
        ours = in_child(run_ours, plate, args.mm_per_px, ours_file)
        cv = in_child(run_opencv, plate, args.mm_per_px, cv_file)
        mesh = in_child(run_ours, panel, args.mm_per_px, panel_file)
        both = ours["ok"] and cv["ok"]
        difference = float(np.mean(np.abs(np.load(ours_file).astype(np.float32) - np.load(cv_file)))) if both else None
        detection = in_child(run_detection, ours_file, args.mm_per_px) if ours["ok"] else {"ok": False}
    results = {
        "mm_per_px": args.mm_per_px,
        "plate_ours": ours,
        "plate_opencv": cv,
        "panel_ours": mesh,
        "plate_mean_abs_difference_grey": difference,
        "detection": detection,
        "ratios": {k: round(ours[k] / cv[k], 3) if both else None for k in ("seconds", "peak_mib")},
    }
    print(f"rectification onto {ours.get('size')} px at {args.mm_per_px} mm/px, one {FRAME[0]}x{FRAME[1]} photo")
    for name, r in (("plate, ours", ours), ("plate, OpenCV undistort+warpPerspective", cv), ("panel mesh, ours", mesh)):
        print(f"  {name:42s} {r['seconds']:7.2f} s  peak {r['peak_mib']:7.0f} MiB")
    print(
        f"  ratio ours/OpenCV (plate): time {results['ratios']['seconds']}, memory {results['ratios']['peak_mib']}; "
        f"mean |difference| {difference:.2f} grey levels"
        if both
        else "  no ratio: a run failed"
    )
    if detection["ok"]:
        print(
            f"detection {detection['detect_s_per_mpx']:.2f} s/MPx, measurement {detection['measure_s_per_mpx']:.2f}"
            f" s/MPx on {detection['megapixels']:.1f} MPx ({detection['cracks']} cracks), "
            f"peak {detection['peak_mib']:.0f} MiB"
        )
    if args.json:
        args.json.write_text(json.dumps(results, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
