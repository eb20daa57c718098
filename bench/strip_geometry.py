"""How true a long strip's adjusted geometry can be: align_frames' adjustment on tie points and GPS fixes drawn
from known frames, without rendering a pixel, over several random draws.

Run by hand from the repository root::

    .venv/bin/python bench/strip_geometry.py [--case 0.5 305 1 --case 0.6 370 2 ...] [--seeds 4]
        [--size 75000 1800] [--ties 400] [--tie-noise-px 0.1] [--gps-noise-m 1.0]

A case is ``OVERLAP FRAMES GAP``: the strip generator's true homographies (``tests.strip_scenes``: each frame's
rotation, scale and perspective drawn independently) at that forward overlap, tie points between every frame
and the next ``GAP`` frames whose overlap is at least 10 % of a frame (``--ties`` spread over the overlap, with
Gaussian noise), GPS fixes of the frame centres with Gaussian noise, then ``adjust_plane`` in strip mode as a
job runs it. Printed per case and draw: every frame corner's error against the truth after one similarity (max
and RMS, native px), and the share of that error's energy a per-frame scale about the frame's centre explains
(the mode that is left when tie points fix each frame to its neighbours and the fixes fix the centres).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import cv2
import numpy as np
from pyproj import Transformer

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # run as a script from a checkout, installed or not

from tests.strip_scenes import _strip_homographies  # noqa: E402
from workers.algorithms.geometry import fit_similarity  # noqa: E402
from workers.algorithms.mosaic import TiePoints, apply_homography, chain_homographies, frame_corners  # noqa: E402
from workers.config import MosaicConfig  # noqa: E402
from workers.records import Frame  # noqa: E402
from workers.stages.align_frames import adjust_plane  # noqa: E402

GSD_M = 0.25  # the camera's ground pixel, m (tests.strip_scenes.make_strip's default)
MIN_OVERLAP = 0.1  # frames further apart than this share of a frame are not tied
TO_WGS84 = Transformer.from_crs(32632, 4326, always_xy=True)


def draw(
    rng: np.random.Generator, args: argparse.Namespace, overlap: float, count: int, gap: int
) -> tuple[list[np.ndarray], dict[int, Frame], dict[tuple[int, int], TiePoints], dict[int, np.ndarray]]:
    """Truth, frames with noisy fixes, tie points, and the start chained from the middle frame."""
    w, h = args.size
    truth = _strip_homographies(rng, count, (w, h), overlap, 0.3, 0.005, 0.002)
    ties, pairwise = {}, {}
    for i in range(count):
        for j in range(i + 1, min(count, i + gap + 1)):
            shared = 1 - (j - i) * (1 - overlap)  # frame i's top rows are frame j's bottom rows (north-bound)
            if shared < MIN_OVERLAP:
                continue
            points = np.column_stack([rng.uniform(0, w - 1, args.ties), rng.uniform(0, (shared - 0.02) * h, args.ties)])
            seen = apply_homography(np.linalg.inv(truth[j]) @ truth[i], points)
            ties[(i, j)] = TiePoints(points, seen + rng.normal(0, args.tie_noise_px, points.shape))
            if j == i + 1:
                pairwise[(i, j)] = cv2.findHomography(ties[(i, j)].points_i, ties[(i, j)].points_j, 0)[0]
    frames = {}
    centre = [[(w - 1) / 2, (h - 1) / 2]]
    for k in range(count):
        gx, gy = apply_homography(truth[k], centre)[0] + rng.normal(0, args.gps_noise_m / GSD_M, 2)
        lon, lat = TO_WGS84.transform(650_000 + GSD_M * gx, 5_200_000 - GSD_M * gy)
        gps = {"lat": lat, "lon": lon, "alt": 8000.0}
        frames[k] = Frame(k, f"strip_{k:05d}.tif", "", w, h, w, h, 1.0, gps=gps, gps_accuracy_m=args.gps_noise_m)
    root = count // 2
    parent = {k: k + 1 if k < root else k - 1 for k in range(count) if k != root}
    return truth, frames, ties, chain_homographies(root, parent, pairwise)


def corner_errors(
    homs: dict[int, np.ndarray], truth: list[np.ndarray], size: tuple[int, int]
) -> tuple[np.ndarray, float]:
    """``(frames, 4, 2)`` corner errors after the similarity that fits all corners best, and the share of their
    energy that a per-frame shift plus scale about the frame's centre explains."""
    corners = frame_corners(*size)
    found = np.concatenate([apply_homography(homs[k], corners) for k in sorted(homs)])
    true = np.concatenate([apply_homography(truth[k], corners) for k in sorted(homs)])
    errors = (apply_homography(fit_similarity(found, true), found) - true).reshape(len(homs), 4, 2)
    offsets = corners - corners.mean(axis=0)  # the corners about the frame's centre
    shifted = errors - errors.mean(axis=1, keepdims=True)
    scale = (shifted * offsets).sum(axis=(1, 2)) / (offsets**2).sum()
    left = shifted - scale[:, None, None] * offsets
    return errors, 1.0 - float((left**2).sum() / (errors**2).sum())


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--case", nargs=3, action="append", metavar=("OVERLAP", "FRAMES", "GAP"), help="default: 0.5 305 1"
    )
    parser.add_argument("--seeds", type=int, default=4, help="random draws per case")
    parser.add_argument("--size", type=int, nargs=2, default=(75000, 1800), metavar=("WIDTH", "HEIGHT"))
    parser.add_argument("--ties", type=int, default=400, help="tie points per tied pair")
    parser.add_argument("--tie-noise-px", type=float, default=0.1)
    parser.add_argument("--gps-noise-m", type=float, default=1.0)
    return parser.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    cases = [(float(o), int(n), int(g)) for o, n, g in (args.case or [("0.5", "305", "1")])]
    print(f"{'overlap':>7} {'frames':>6} {'gap':>3} {'seed':>4} {'max px':>7} {'RMS px':>7} {'scale':>6} {'s':>6}")
    for overlap, count, gap in cases:
        worst = []
        for seed in range(args.seeds):
            truth, frames, ties, start = draw(np.random.default_rng(seed), args, overlap, count, gap)
            started = time.perf_counter()
            homs = adjust_plane(MosaicConfig(mode="strip"), frames, start, count // 2, ties)
            seconds = time.perf_counter() - started
            errors, scale_share = corner_errors(homs, truth, tuple(args.size))
            distance = np.linalg.norm(errors, axis=2)
            worst.append(distance.max())
            print(
                f"{overlap:7.2f} {count:6d} {gap:3d} {seed:4d} {distance.max():7.2f} "
                f"{np.sqrt(np.mean(distance**2)):7.2f} {scale_share:6.2f} {seconds:6.1f}",
                flush=True,
            )
        print(f"{overlap:7.2f} {count:6d} {gap:3d}  max over draws: median {np.median(worst):.2f} px", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
