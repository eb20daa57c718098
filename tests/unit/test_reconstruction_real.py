"""``reconstruct`` on real photos (../shared/data/sfm_opensfm): OpenSfM's lund street sequence (29 frames,
phone GPS) and berlin (3 frames with ground control points).

Features: OpenCV SIFT (RootSIFT, ``matching.detect_sift``) at a reduced size, mutual ratio-test matches
(``matching.match_ratio``) filtered by a USAC fundamental matrix, pairs from flight order and GPS
neighbours (``pairing.candidate_pairs``), as OpenSfM's config for lund does (4 GPS neighbours).
Initial focal length from the EXIF 35 mm equivalent. Phone GPS: 5 m horizontal; the altitude of a
phone is no better than its vertical datum, so it gets 100 m (OpenSfM ignores it by default).
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from tests.conftest import shared_data
from workers.algorithms.geometry import Camera, lonlat_to_utm, utm_epsg
from workers.algorithms.mosaic import candidate_pairs, detect_sift, match_ratio
from workers.algorithms.sfm import (
    GpsFix,
    LocalFrame,
    Reconstruction,
    ReconstructionOptions,
    parse_opensfm_gcps,
    reconstruct,
    scale_observations,
)
from workers.image_meta import inspect_image

pytestmark = pytest.mark.realdata


def load_flight(folder: Path, max_side: int, max_features: int) -> dict:
    """Names, metadata, working size, features and descriptors of every JPEG in ``folder``."""
    paths = sorted(p for p in folder.iterdir() if p.suffix.lower() == ".jpg")
    metas = [inspect_image(p) for p in paths]
    features, descriptors = [], []
    for path in paths:
        gray = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        scale = max_side / max(gray.shape)
        if scale < 1.0:
            gray = cv2.resize(gray, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
        xy, desc = detect_sift(gray, max_features)
        features.append(xy.astype(np.float64))
        descriptors.append(desc)
    return {
        "names": [p.name for p in paths],
        "metas": metas,
        "size": (gray.shape[1], gray.shape[0]),
        "features": features,
        "descriptors": descriptors,
    }


def local_gps(metas: list[dict]) -> tuple[LocalFrame, np.ndarray]:
    """The job's local frame (UTM zone of the first fix, origin at the rounded mean) and (N, 3) positions."""
    lla = np.array([[m["gps"]["lon"], m["gps"]["lat"], m["gps"]["alt"]] for m in metas])
    epsg = utm_epsg(lla[0, 1], lla[0, 0])
    e0, n0 = np.round(lonlat_to_utm(lla[:, :2], epsg).mean(axis=0))
    frame = LocalFrame(epsg, float(e0), float(n0))
    return frame, frame.from_lonlat(lla)


def match_pairs(flight: dict, pairs: list[tuple[int, int]]) -> dict:
    matches = {}
    for i, j in pairs:
        m = match_ratio(flight["descriptors"][i], flight["descriptors"][j], 0.8)
        if len(m) < 20:
            continue
        a, b = flight["features"][i][m[:, 0]], flight["features"][j][m[:, 1]]
        cv2.setRNGSeed(len(m))
        F, mask = cv2.findFundamentalMat(a, b, cv2.USAC_MAGSAC, 1.5, 0.999, 10000)
        if F is not None and mask is not None and mask.sum() >= 20:
            keep = mask.ravel().astype(bool)
            matches[(i, j)] = (m[keep, 0], m[keep, 1])
    return matches


def exif_camera(flight: dict) -> Camera:
    w, h = flight["size"]
    f = flight["metas"][0]["focal_length_35mm"] / 36.0 * max(w, h)
    return Camera(w, h, f, f, (w - 1) / 2.0, (h - 1) / 2.0)


@pytest.fixture(scope="module")
def lund() -> tuple[dict, Reconstruction]:
    flight = load_flight(shared_data("sfm_opensfm/lund") / "images", max_side=1024, max_features=2000)
    _, enu = local_gps(flight["metas"])
    matches = match_pairs(flight, candidate_pairs(len(enu), enu[:, :2], max_gap=3, neighbours=4, exhaustive_max=0))
    gps = {k: GpsFix(tuple(enu[k]), sigma_h=5.0, sigma_v=100.0) for k in range(len(enu))}
    # no self-calibration: a forward-moving street sequence hardly constrains the focal length
    rec = reconstruct(flight["features"], matches, exif_camera(flight), gps=gps, frame_names=flight["names"])
    return flight, rec


def test_lund_registers_every_frame_with_subpixel_residuals(lund) -> None:
    flight, rec = lund
    report = rec.report
    assert report["frames"]["registered"] == 29, report["frames"]["not_registered"]
    assert report["rms_reprojection_px"] < 1.5
    assert all(f["rms_px"] < 1.5 and f["observations"] >= 20 for f in report["per_frame"].values())
    assert len(rec.points) > 1500 and report["world_frame"].startswith("local")
    json.dumps(report)


def test_lund_gps_residuals_are_reported_and_phone_sized(lund) -> None:
    _, rec = lund
    horizontal = [np.hypot(*f["gps_residual_enu_m"][:2]) for f in rec.report["per_frame"].values()]
    assert len(horizontal) == 29
    assert np.median(horizontal) < 6.0 and max(horizontal) < 20.0  # 5 m phone GPS


@pytest.fixture(scope="module")
def berlin() -> tuple[dict, Reconstruction]:
    root = shared_data("sfm_opensfm/berlin")
    flight = load_flight(root / "images", max_side=1600, max_features=4000)
    frame, enu = local_gps(flight["metas"])
    full = {n: (m["width"], m["height"]) for n, m in zip(flight["names"], flight["metas"], strict=True)}
    gcps = parse_opensfm_gcps((root / "ground_control_points.json").read_text(), full, frame)
    gcps = scale_observations(gcps, flight["size"][0] / flight["metas"][0]["width"])
    matches = match_pairs(flight, [(0, 1), (0, 2), (1, 2)])
    gps = {k: GpsFix(tuple(enu[k]), sigma_h=5.0, sigma_v=100.0) for k in range(3)}
    # the sample's GCP positions agree with each other only to metres: say so
    rec = reconstruct(
        flight["features"],
        matches,
        exif_camera(flight),
        gps=gps,
        gcps=gcps,
        frame_names=flight["names"],
        options=ReconstructionOptions(gcp_sigma_m=1.0),
    )
    return flight, rec


def test_berlin_with_ground_control(berlin) -> None:
    _, rec = berlin
    report = rec.report
    assert report["frames"]["registered"] == 3 and report["rms_reprojection_px"] < 1.5
    gcps = report["gcps"]
    assert {k: v["role"] for k, v in gcps.items()} == {"0": "control", "1": "tie", "3": "control"}
    for gid in ("0", "3"):
        assert gcps[gid]["rms_px"] < 5.0 and gcps[gid]["residual_m"] < 10.0
    assert gcps["1"]["rms_px"] < 2.0 and gcps["1"]["observations"] == 2


def _berlin_ortho_job(folder: Path, options: dict) -> str:
    """The berlin photos and their control points as an ortho job (as the API lays one out) up to its
    photo-triangulation; what that stage says."""
    from workers.config import build_config
    from workers.pipeline import PipelineError, _inspect, pipeline_key, run_stage, stage_names
    from workers.workspace import JobWorkspace

    root = shared_data("sfm_opensfm/berlin")
    ws = JobWorkspace(folder)
    ws.save_config(build_config("mosaic", options).model_dump())
    ws.save_inputs([_inspect(p) for p in sorted((root / "images").glob("*.jpg"))])
    ws.gcp_dir().mkdir(parents=True, exist_ok=True)
    (ws.gcp_dir() / "ground_control_points.json").write_bytes((root / "ground_control_points.json").read_bytes())
    pipeline = pipeline_key("mosaic", options)
    stages = stage_names(pipeline)
    try:
        for name in stages[: stages.index("adjust_bundle") + 1]:
            run_stage(ws, pipeline, name)
    except PipelineError as exc:
        return str(exc)
    return f"registered {ws.load_stage_report('adjust_bundle')['registered']}"


def test_control_held_too_tightly_is_named_when_the_triangulation_fails(tmp_path: Path) -> None:
    # the sample's control points agree with each other only to metres (see berlin above)
    failed = _berlin_ortho_job(tmp_path / "tight", {"mode": "ortho"})
    assert "from its GPS position" in failed and "held to gcp_sigma_m 0.02 m" in failed, failed
    assert _berlin_ortho_job(tmp_path / "loose", {"mode": "ortho", "gcp_sigma_m": 1.0}) == "registered 3"
