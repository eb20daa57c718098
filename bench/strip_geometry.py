"""How true a long strip's adjusted geometry can be: align_frames' adjustment on tie points and GPS fixes drawn
from known frames, without rendering a pixel, over several random draws.

Run by hand from the repository root::

    .venv/bin/python bench/strip_geometry.py [--case 0.5 305 1 --case 0.6 370 2 ...] [--seeds 4]
        [--size 75000 1800] [--ties 400] [--tie-noise-px 0.1] [--gps-noise-m 1.0]

A case is ``OVERLAP FRAMES GAP``, drawn by ``tests.strip_scenes.adjustment_inputs``: the strip generator's true
homographies (each frame's rotation, scale and perspective drawn independently) at that forward overlap, tie
points between every frame and the next ``GAP`` frames whose overlap is at least 10 % of a frame (``--ties``
spread over the overlap, with Gaussian noise), GPS fixes of the frame centres with Gaussian noise, then
``adjust_plane`` in strip mode as a job runs it. Printed per case and draw: every frame corner's error against
the truth after one similarity (max and RMS, native px), and the share of that error's energy a per-frame scale
about the frame's centre explains (the mode that is left when tie points fix each frame to its neighbours and
the fixes fix the centres).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # run as a script from a checkout, installed or not

from tests.strip_scenes import adjustment_inputs  # noqa: E402
from workers.algorithms.geometry import fit_similarity  # noqa: E402
from workers.algorithms.mosaic import apply_homography, frame_corners  # noqa: E402
from workers.config import MosaicConfig  # noqa: E402
from workers.stages.align_frames import adjust_plane  # noqa: E402

GSD_M = 0.25  # the camera's ground pixel, m (tests.strip_scenes.make_strip's default)


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
            truth, frames, ties, start = adjustment_inputs(
                seed,
                count,
                tuple(args.size),
                overlap,
                GSD_M,
                gap=gap,
                ties_per_pair=args.ties,
                tie_noise_px=args.tie_noise_px,
                gps_noise_m=args.gps_noise_m,
            )
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
