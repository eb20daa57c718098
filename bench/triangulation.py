"""Our photo-triangulation (``workers.algorithms.sfm.reconstruction.reconstruct``) against COLMAP's incremental
mapper (``pycolmap.incremental_mapping``) on the same features and verified matches.

Run by hand from the repository root (never in CI)::

    .venv/bin/pip install pycolmap        # the reference; NOT a dependency of the project
    .venv/bin/python bench/triangulation.py [--max-px 1600] [--features 4000] [--json OUT]

Datasets: ``../shared/data/sfm_opensfm/lund`` (29 street photos, phone GPS) and
``../shared/data/drone_brighton_strip1`` (6 nadir DJI frames, GPS + gimbal attitude); a missing folder is
skipped with a message. For each, pycolmap extracts SIFT (longest side ``--max-px``, ``--features`` per
image, one shared SIMPLE_RADIAL camera whose focal length prior is set from the EXIF 35 mm equivalent, as
ours is) and matches sequential pairs (overlap 10, quadratic) with its two-view verification into a database;
then, each in its own spawned child process, (a) COLMAP's incremental mapper reads that database (its
initial-pair and registration inlier minimums lowered to 50 and 15 and its initial pair allowed 5 degrees
and forward motion, near ours) and
(b) ``reconstruct`` gets the same keypoints and inlier matches, the EXIF focal length, the GPS fixes
(5 m horizontal, 100 m vertical for a phone; 3 m and 5 m for the drone) and the DJI attitude, refining
focal length and k1 as COLMAP does (SIMPLE_RADIAL). Wall time is the mapper alone, in its child.
RMS reprojection is the root mean square length of every observation's residual, px, computed the same
way for both. Ratios are ours / COLMAP: time below 1.00 means we are faster.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # tiny BLAS calls in lsmr: threads cost more than they give
ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"
DATASETS = {"lund": DATA / "sfm_opensfm" / "lund" / "images", "brighton": DATA / "drone_brighton_strip1"}
sys.path.insert(0, str(ROOT))


def prepare(images: Path, db: Path, max_px: int, features: int) -> dict[str, Any]:
    """pycolmap SIFT + sequential matching with geometric verification into ``db``; seconds and counts."""
    import pycolmap

    names = sorted(p.name for p in images.iterdir() if p.suffix.lower() in (".jpg", ".jpeg"))
    options = pycolmap.FeatureExtractionOptions()
    options.max_image_size, options.sift.max_num_features = max_px, features
    started = time.perf_counter()
    pycolmap.extract_features(
        db, images, image_names=names, camera_mode=pycolmap.CameraMode.SINGLE, extraction_options=options
    )
    extracted = time.perf_counter()
    database = pycolmap.Database.open(db)
    for camera in database.read_all_cameras():  # the same EXIF focal length prior as ours, before verification
        camera.params = [exif_focal_px(images / names[0]), camera.width / 2, camera.height / 2, 0.0]
        camera.has_prior_focal_length = True
        database.update_camera(camera)
    database.close()
    pycolmap.match_sequential(db, pairing_options=pycolmap.SequentialPairingOptions(overlap=10))
    matched = time.perf_counter()
    return {"names": names, "extract_s": extracted - started, "match_s": matched - extracted}


def exif_focal_px(path: Path) -> float:
    """Focal length in pixels of the full image from the EXIF 35 mm equivalent (36 mm wide frame)."""
    from workers.image_meta import inspect_image

    meta = inspect_image(path)
    return float(meta["focal_length_35mm"]) / 36.0 * max(meta["width"], meta["height"])


def read_database(db: Path, names: list[str]) -> tuple[list[Any], dict]:
    """Keypoints per image in OpenCV pixels (COLMAP puts the first pixel's centre at 0.5) and the verified
    inlier matches per image pair, indexed like ``names``."""
    import numpy as np
    import pycolmap

    database = pycolmap.Database.open(db)
    index = {image.image_id: names.index(image.name) for image in database.read_all_images()}
    keypoints = [None] * len(names)
    for image_id, k in index.items():
        keypoints[k] = np.asarray(database.read_keypoints(image_id))[:, :2].astype(np.float64) - 0.5
    matches = {}
    for pair_id, geometry in zip(*database.read_two_view_geometries(), strict=True):
        a, b = pycolmap.pair_id_to_image_pair(pair_id)
        inliers = np.asarray(geometry.inlier_matches)
        if len(inliers) >= 15:
            i, j = index[a], index[b]
            matches[(i, j) if i < j else (j, i)] = (
                (inliers[:, 0], inliers[:, 1]) if i < j else (inliers[:, 1], inliers[:, 0])
            )
    database.close()
    return keypoints, matches


def run_colmap(db: str, images: str, names: list[str]) -> dict[str, Any]:
    """Child: COLMAP's incremental mapper; the largest model it makes."""
    import pycolmap

    options = pycolmap.IncrementalPipelineOptions()
    # thresholds near ours (min_pair_inliers 20, min_pnp_inliers 12, initial angle 5 degrees, forward motion
    # allowed): COLMAP's defaults (100 and 30 inliers, 16 degrees, no forward motion) stop lund's street sequence
    options.mapper.init_min_num_inliers, options.mapper.abs_pose_min_num_inliers = 50, 15
    options.mapper.init_min_tri_angle, options.mapper.init_max_forward_motion = 5.0, 1.0
    with tempfile.TemporaryDirectory() as out:
        started = time.perf_counter()
        models = pycolmap.incremental_mapping(db, images, out, options)
        seconds = time.perf_counter() - started
    if not models:
        return {"ok": False, "status": "no model", "seconds": seconds}
    model = max(models.values(), key=lambda m: m.num_reg_images())
    squares = []
    for point in model.points3D.values():
        for element in point.track.elements:
            image = model.images[element.image_id]
            projected = image.project_point(point.xyz)
            if projected is not None:
                squares.append(float(((projected - image.points2D[element.point2D_idx].xy) ** 2).sum()))
    camera = next(iter(model.cameras.values()))
    return {
        "ok": True,
        "status": f"{len(models)} model(s)",
        "seconds": seconds,
        "registered": model.num_reg_images(),
        "total": len(names),
        "points": model.num_points3D(),
        "observations": len(squares),
        "rms_px": (sum(squares) / max(len(squares), 1)) ** 0.5,
        "focal_ratio": float(camera.params[0]) / exif_focal_px(Path(images) / names[0]),
    }


def run_ours(db: str, images: str, names: list[str], dataset: str) -> dict[str, Any]:
    """Child: ``reconstruct`` on the database's keypoints and verified matches, with EXIF GPS (+ attitude)."""
    import numpy as np

    from workers.algorithms.geometry import Camera, lonlat_to_utm, utm_epsg
    from workers.algorithms.sfm import Attitude, GpsFix, LocalFrame, ReconstructionOptions, reconstruct
    from workers.image_meta import inspect_image

    keypoints, matches = read_database(Path(db), names)
    metas = [inspect_image(Path(images) / n) for n in names]
    w, h = metas[0]["width"], metas[0]["height"]
    f = exif_focal_px(Path(images) / names[0])
    lla = np.array([[m["gps"]["lon"], m["gps"]["lat"], m["gps"]["alt"]] for m in metas])
    epsg = utm_epsg(lla[0, 1], lla[0, 0])
    e0, n0 = np.round(lonlat_to_utm(lla[:, :2], epsg).mean(axis=0))
    enu = LocalFrame(epsg, float(e0), float(n0)).from_lonlat(lla)
    sigma = (3.0, 5.0) if dataset == "brighton" else (5.0, 100.0)
    gps = {k: GpsFix(tuple(enu[k]), *sigma) for k in range(len(names))}
    attitude = {
        k: Attitude(m["yaw"], m["pitch"], m["roll"] or 0.0)
        for k, m in enumerate(metas)
        if m.get("yaw") is not None and m.get("pitch") is not None
    }
    started = time.perf_counter()
    rec = reconstruct(
        keypoints,
        matches,
        Camera(w, h, f, f, (w - 1) / 2, (h - 1) / 2),
        gps=gps,
        attitude=attitude,
        frame_names=names,
        options=ReconstructionOptions(refine_focal=True, refine_k1=True),
    )
    seconds = time.perf_counter() - started
    report = rec.report
    return {
        "ok": True,
        "status": report.get("initialisation", ""),
        "seconds": seconds,
        "registered": report["frames"]["registered"],
        "total": len(names),
        "points": report["points"],
        "observations": report.get("observations", 0),
        "rms_px": report["rms_reprojection_px"],
        "focal_ratio": rec.camera.fx / f,
        "k1": rec.camera.k1,
    }


def in_child(target: Any, *args: Any) -> dict[str, Any]:
    pool = mp.get_context("spawn").Pool(1)
    try:
        return pool.apply(target, args)
    except Exception as exc:  # a benchmark reports the failure instead of dying
        return {"ok": False, "status": f"{type(exc).__name__}: {exc}"}
    finally:  # let the child exit by itself: pycolmap prints a stack trace when it is terminated
        pool.close()
        pool.join()


def table(rows: list[dict[str, Any]]) -> str:
    head = (
        f"{'dataset':9} {'mapper':7} {'seconds':>8} {'registered':>10} {'points':>7} {'obs':>7} {'RMS px':>7}"
        f" {'f/EXIF':>6}  status"
    )
    lines = [head, "-" * len(head)]
    for r in rows:
        reg = f"{r.get('registered', '-')}/{r.get('total', '-')}"
        lines.append(
            f"{r['dataset']:9} {r['mapper']:7} {r.get('seconds', float('nan')):8.2f} {reg:>10} "
            f"{r.get('points', '-'):>7} {r.get('observations', '-'):>7} {r.get('rms_px') or float('nan'):7.3f}"
            f" {r.get('focal_ratio') or float('nan'):6.3f}  {r['status']}"
        )
    return "\n".join(lines)


def ratios(rows: list[dict[str, Any]]) -> str:
    lines = ["ratios ours / COLMAP (time < 1.00: we are faster)"]
    for name in dict.fromkeys(r["dataset"] for r in rows):
        ours = next(r for r in rows if r["dataset"] == name and r["mapper"] == "ours")
        ref = next(r for r in rows if r["dataset"] == name and r["mapper"] == "colmap")
        if ours["ok"] and ref["ok"] and ours.get("rms_px") and ref.get("rms_px"):
            lines.append(
                f"{name:9} time {ours['seconds'] / ref['seconds']:.2f}  registered "
                f"{ours['registered']}/{ref['registered']}  RMS {ours['rms_px'] / ref['rms_px']:.2f}"
            )
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--max-px", type=int, default=1600, help="longest image side for SIFT, px")
    parser.add_argument("--features", type=int, default=4000, help="SIFT features per image")
    parser.add_argument("--json", type=Path, help="also write the rows as JSON here")
    args = parser.parse_args()
    try:
        import pycolmap  # noqa: F401
    except ImportError:
        sys.exit("pycolmap is not installed: .venv/bin/pip install pycolmap (the benchmark's reference only)")
    rows = []
    for name, images in DATASETS.items():
        if not images.is_dir():
            print(f"skipping {name}: {images} is absent (see shared/data/MANIFEST.md)")
            continue
        with tempfile.TemporaryDirectory() as tmp:
            db = Path(tmp) / "database.db"
            prep = prepare(images, db, args.max_px, args.features)
            print(f"{name}: pycolmap SIFT {prep['extract_s']:.1f} s, matching {prep['match_s']:.1f} s")
            for mapper, target, extra in (("colmap", run_colmap, ()), ("ours", run_ours, (name,))):
                result = in_child(target, str(db), str(images), prep["names"], *extra)
                rows.append({"dataset": name, "mapper": mapper, **result})
    print(table(rows))
    print(ratios(rows))
    if args.json:
        args.json.write_text(json.dumps(rows, indent=2))


if __name__ == "__main__":
    main()
