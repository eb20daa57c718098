"""Disparity maps on the Middlebury pairs: OpenCV's StereoSGBM (the issue's reference settings)
against our ``sgbm`` and ``local`` matchers, in the same run.

Run by hand from the repository root::

    .venv/bin/python bench/stereo.py [--data ../shared/data/stereo_middlebury] [--repeats 3]

For every pair it prints the dense bad-pixel rate (error > 1 px or no value, over ground-truth
pixels, non-occluded where the set has a mask), the rate over valued pixels only, the density, the
ratio of the dense rate to the reference's, and seconds per megapixel (median of ``--repeats`` runs
after one warm-up). ``local`` runs on NumPy, and again on CuPy where a CUDA device is present.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from gpu_kernels.backend import cuda_available  # noqa: E402
from workers.algorithms.disparity import (  # noqa: E402
    REFERENCE,
    StereoPair,
    local,
    opencv_sgbm,
    read_pair,
    score_disparity,
    sgbm,
)

NUM_DISPARITIES = 64  # the reference's range, for every method


def seconds(fn: Callable[[], object], repeats: int) -> float:
    """Median wall time of ``repeats`` calls after one warm-up (compilation, caches)."""
    fn()
    times = []
    for _ in range(repeats):
        started = time.perf_counter()
        fn()
        times.append(time.perf_counter() - started)
    return statistics.median(times)


def methods(pair: StereoPair) -> dict[str, Callable[[], np.ndarray]]:
    """Method name -> a call giving its dense (what is scored) map of ``pair``."""
    a, b = pair.left, pair.right
    out: dict[str, Callable[[], np.ndarray]] = {
        "opencv-sgbm (reference)": lambda: opencv_sgbm(a, b, NUM_DISPARITIES, params=REFERENCE),
        "sgbm": lambda: sgbm(a, b, NUM_DISPARITIES).dense,
        "sgbm unfilled": lambda: sgbm(a, b, NUM_DISPARITIES, fill=False).dense,
        "local cpu": lambda: local(a, b, NUM_DISPARITIES).dense,
        "local cpu unfilled": lambda: local(a, b, NUM_DISPARITIES, fill=False).dense,
    }
    if cuda_available():
        import cupy  # noqa: PLC0415 - only where a GPU stack is installed

        def on_gpu() -> np.ndarray:
            result = local(a, b, NUM_DISPARITIES, device="cuda").dense
            cupy.cuda.Device().synchronize()
            return result

        out["local cuda"] = on_gpu
    return out


def bench_pair(pair: StereoPair, repeats: int) -> None:
    megapixels = pair.left.shape[0] * pair.left.shape[1] / 1e6
    print(f"\n{pair.name}  {pair.left.shape[1]}x{pair.left.shape[0]}  mask: {pair.mask is not None}")
    print(f"{'method':26s} {'dense bad':>9s} {'valid bad':>9s} {'density':>8s} {'x ref':>6s} {'s/MP':>7s}")
    reference = None
    for name, fn in methods(pair).items():
        s = score_disparity(fn(), pair.truth, pair.mask)
        reference = s.bad if reference is None else reference
        t = seconds(fn, repeats) / megapixels
        print(
            f"{name:26s} {100 * s.bad:8.1f}% {100 * s.valid_bad:8.1f}% {100 * s.density:7.1f}% "
            f"{s.bad / reference:6.2f} {t:7.2f}"
        )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=ROOT.parent / "shared" / "data" / "stereo_middlebury")
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    folders = sorted(p for p in args.data.iterdir() if p.is_dir()) if args.data.is_dir() else []
    if not folders:
        sys.exit(f"no Middlebury pairs under {args.data}")
    print(f"CUDA device: {cuda_available()}; {NUM_DISPARITIES} disparities")
    for folder in folders:
        bench_pair(read_pair(folder), args.repeats)


if __name__ == "__main__":
    main()
