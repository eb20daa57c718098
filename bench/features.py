"""Feature detectors on the same frames, as the source work compared them: detect time per frame, matches,
homography inliers and registration error against a planted homography, at 640x360, 1280x720, 1920x1080 and at
the frames' full size.

Run by hand from the repository root::

    .venv/bin/python bench/features.py [DIR] [--frames 2] [--sizes 640 1280 1920 0] [--json OUT]

Frames: the first ``--frames`` photos of ``DIR`` (default ``../shared/data/drone_brighton_strip1``, 4000 x 2250).
Each is resized (area average) to each width of ``--sizes`` (0: full size) and warped by a planted homography
(3 degrees of rotation, 0.95 scale, a perspective tilt that moves corners about 1 %, 12 % shift), and the pair
(frame, warped frame) is registered by each method as the pipeline does: ``sift`` (OpenCV SIFT, FLANN, ratio 0.75
both ways), ``orb`` (OpenCV ORB, FAST threshold 10, Hamming, ratio 0.75 both ways), ``harris_ncc`` (our Harris
corners matched by normalised cross-correlation of 15 px windows, NCC >= 0.85; not rotation invariant, meant for
strips that keep their heading), and ``akaze`` when this OpenCV has it (``cv2.AKAZE_create`` in OpenCV 4, the
contrib build's ``cv2.xfeatures2d.AKAZE_create`` in OpenCV 5; MLDB bit strings, Hamming). Keypoints are capped at
6000 (ORB 2000, the pipeline's). Inliers: USAC MAGSAC++ at 2 px of the size measured. Registration error: RMS over
a 10 x 10 grid of the distance between the found and the planted homography's mapping, px of that size.
Times are wall seconds per frame, the best of ``--repeats``, on one thread of OpenCV's (``cv2.setNumThreads(1)``)
so the methods compare on the same footing; the reference is OpenCV's SIFT in the same run (time x: / SIFT's).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_DIR = ROOT.parent / "shared" / "data" / "drone_brighton_strip1"
sys.path.insert(0, str(ROOT))  # run as a script from a checkout, installed or not

from workers.algorithms.mosaic import detect, estimate_homography, match  # noqa: E402

MAX_FEATURES = {"sift": 6000, "orb": 2000, "harris_ncc": 6000, "akaze": 6000}


def akaze_detector() -> Any | None:
    """OpenCV's AKAZE where this build has it: the main module (OpenCV 4) or the contrib one (OpenCV 5)."""
    if hasattr(cv2, "AKAZE_create"):
        return cv2.AKAZE_create()
    contrib = getattr(cv2, "xfeatures2d", None)
    return contrib.AKAZE_create() if contrib is not None and hasattr(contrib, "AKAZE_create") else None


def detect_akaze(detector: Any, gray: np.ndarray, limit: int) -> tuple[np.ndarray, np.ndarray]:
    keypoints, desc = detector.detectAndCompute(gray, None)
    if desc is None or not keypoints:
        return np.zeros((0, 2), np.float32), np.zeros((0, 61), np.uint8)
    order = np.argsort([-kp.response for kp in keypoints])[:limit]
    return np.array([keypoints[i].pt for i in order], np.float32), np.ascontiguousarray(desc[order], np.uint8)


def planted(width: int, height: int) -> np.ndarray:
    """(3, 3) the planted homography at a ``width`` x ``height`` size: the same motion, in that size's px."""
    to_unit = np.array([[1 / width, 0, -0.5], [0, 1 / width, -0.5 * height / width], [0, 0, 1]])
    angle = math.radians(3.0)
    c, s = 0.95 * math.cos(angle), 0.95 * math.sin(angle)
    motion = np.array([[c, -s, 0.12], [s, c, 0.03], [0.02, -0.015, 1.0]])
    return np.linalg.inv(to_unit) @ motion @ to_unit


def registration_error(found: np.ndarray | None, truth: np.ndarray, width: int, height: int) -> float:
    if found is None:
        return float("nan")
    xs, ys = np.meshgrid(np.linspace(0, width - 1, 10), np.linspace(0, height - 1, 10))
    grid = np.column_stack([xs.ravel(), ys.ravel(), np.ones(xs.size)])
    a, b = grid @ found.T, grid @ truth.T
    return float(np.sqrt(np.mean(np.sum((a[:, :2] / a[:, 2:] - b[:, :2] / b[:, 2:]) ** 2, axis=1))))


def run_method(method: str, pairs: list[tuple[np.ndarray, np.ndarray, np.ndarray]], repeats: int) -> dict[str, Any]:
    """Mean figures of ``method`` over the (frame, warped, planted homography) pairs of one size."""
    akaze = akaze_detector() if method == "akaze" else None
    feature_type = "orb" if method == "akaze" else method  # AKAZE's bit strings match as ORB's do (Hamming)

    def find(gray: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        if akaze is not None:
            return detect_akaze(akaze, gray, MAX_FEATURES[method])
        return detect(gray, method, "cpu", MAX_FEATURES[method])  # type: ignore[arg-type]

    seconds, matches, inliers, errors = [], [], [], []
    for a, b, truth in pairs:
        best = math.inf
        for _ in range(repeats):
            started = time.perf_counter()
            (pa, da), (pb, db) = find(a), find(b)
            best = min(best, (time.perf_counter() - started) / 2)
        seconds.append(best)
        pairs_found = match(da, db, feature_type, "cpu", 0.75, 0.85)  # type: ignore[arg-type]
        H, inlier = estimate_homography(pa[pairs_found[:, 0]], pb[pairs_found[:, 1]], 2.0)
        matches.append(len(pairs_found))
        inliers.append(int(inlier.sum()))
        errors.append(registration_error(H, truth, a.shape[1], a.shape[0]))
    return {"seconds": float(np.mean(seconds)), "matches": float(np.mean(matches)),
            "inliers": float(np.mean(inliers)), "error_px": float(np.nanmean(errors)) if not np.all(np.isnan(errors))
            else float("nan")}  # fmt: skip


def make_pairs(paths: list[Path], width: int) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    pairs = []
    for path in paths:
        gray = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        if width:
            gray = cv2.resize(gray, (width, round(gray.shape[0] * width / gray.shape[1])), interpolation=cv2.INTER_AREA)
        h, w = gray.shape
        truth = planted(w, h)
        pairs.append((gray, cv2.warpPerspective(gray, truth, (w, h), flags=cv2.INTER_LINEAR), truth))
    return pairs


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dir", nargs="?", type=Path, default=DEFAULT_DIR, help="folder of frames")
    parser.add_argument("--frames", type=int, default=2, help="frames used (each warped once)")
    parser.add_argument("--sizes", type=int, nargs="*", default=[640, 1280, 1920, 0], help="widths; 0: full size")
    parser.add_argument("--repeats", type=int, default=2, help="detections per frame; the fastest counts")
    parser.add_argument("--json", type=Path, default=None, help="also save the figures here")
    return parser.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    paths = sorted(p for p in args.dir.iterdir() if p.suffix.lower() in {".jpg", ".jpeg", ".png", ".tif"})
    if not paths:
        sys.exit(f"{args.dir}: no frames (the default needs ../shared/data)")
    cv2.setNumThreads(1)
    methods = ["sift", "orb", "harris_ncc"] + (["akaze"] if akaze_detector() is not None else [])
    if "akaze" not in methods:
        print("akaze: not in this OpenCV build (OpenCV 5 keeps it in opencv-contrib-python-headless)")
    rows = []
    for width in args.sizes:
        pairs = make_pairs(paths[: args.frames], width)
        size = f"{pairs[0][0].shape[1]}x{pairs[0][0].shape[0]}"
        for method in methods:
            rows.append({"size": size, "method": method, **run_method(method, pairs, args.repeats)})
            print(f"  {size} {method}: done", flush=True)
    print(f"{'size':>10} {'method':11}{'ms/frame':>9}{'time x':>8}{'matches':>9}{'inliers':>9}{'error px':>9}")
    for row in rows:
        sift = next(r for r in rows if r["size"] == row["size"] and r["method"] == "sift")
        ratio = row["seconds"] / sift["seconds"]
        print(f"{row['size']:>10} {row['method']:11}{1000 * row['seconds']:>9.1f}{ratio:>8.2f}"
              f"{row['matches']:>9.0f}{row['inliers']:>9.0f}{row['error_px']:>9.3f}")  # fmt: skip
    print(
        f"OpenCV {cv2.__version__}, one thread; time x: / SIFT's at the same size;",
        f"{args.frames} frames of {args.dir.name}",
    )
    if args.json:
        args.json.write_text(json.dumps(rows, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
