"""gpu_kernels against OpenCV on the same inputs, in the same run: Harris, SIFT and descriptor matching.

Run by hand from the repository root::

    .venv/bin/python bench/kernels.py [--large] [--json OUT]

Each case runs in its own spawned child process (its peak memory, VmHWM, is that case's alone):
ours on CuPy when a CUDA device is present, else on NumPy, then OpenCV's CPU function. Times are the
median of 3 runs after one warm-up. Inputs are generated on the host with fixed seeds.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.mosaic_vs_opencv import in_child, peak_rss_mib  # noqa: E402


def timed(fn: Any, sync: Any = None) -> float:
    fn()  # warm-up: kernel compilation, caches
    times = []
    for _ in range(3):
        started = time.perf_counter()
        fn()
        if sync is not None:
            sync()
        times.append(time.perf_counter() - started)
    return statistics.median(times)


def device_xp() -> tuple[Any, Any, str]:
    from gpu_kernels.backend import cuda_available

    if cuda_available():
        import cupy

        return cupy, cupy.cuda.Device().synchronize, "cupy"
    import numpy

    return numpy, None, "numpy"


def harris_case(height: int, width: int, who: str) -> dict[str, Any]:
    import cv2

    from gpu_kernels.harris import harris_response
    from tests.gpu.kernel_cases import textured_image

    img = textured_image(height, width, seed=0)
    if who == "opencv":
        seconds = timed(lambda: cv2.cornerHarris(img, 3, 3, 0.04))
        return {"seconds": seconds, "peak_mib": peak_rss_mib(), "backend": "opencv"}
    xp, sync, backend = device_xp()
    dev = xp.asarray(img)
    seconds = timed(lambda: harris_response(dev, 0.04, "box", 1 / (4 * 3 * 255)), sync)
    return {"seconds": seconds, "peak_mib": peak_rss_mib(), "backend": backend}


def sift_case(height: int, width: int, who: str) -> dict[str, Any]:
    import cv2

    from gpu_kernels.sift import sift
    from tests.gpu.kernel_cases import textured_image

    img = textured_image(height, width, seed=0)
    if who == "opencv":
        detector = cv2.SIFT_create()
        seconds = timed(lambda: detector.detectAndCompute(img, None))
        return {"seconds": seconds, "peak_mib": peak_rss_mib(), "backend": "opencv"}
    xp, sync, backend = device_xp()
    dev = xp.asarray(img)
    seconds = timed(lambda: sift(dev), sync)
    return {"seconds": seconds, "peak_mib": peak_rss_mib(), "backend": backend}


def match_case(n: int, dim: int, masked: bool, who: str) -> dict[str, Any]:
    import cv2
    import numpy as np

    from gpu_kernels.bf_match import match_descriptors
    from gpu_kernels.masks import same_value

    rng = np.random.default_rng(0)
    a, b = rng.random((n, dim), dtype=np.float32), rng.random((n, dim), dtype=np.float32)
    octave_a, octave_b = rng.integers(0, 4, n), rng.integers(0, 4, n)
    if who == "opencv":
        mask = same_value(octave_a, octave_b).astype(np.uint8) if masked else None
        matcher = cv2.BFMatcher(cv2.NORM_L2)
        seconds = timed(lambda: matcher.knnMatch(a, b, k=2, mask=mask))
        return {"seconds": seconds, "peak_mib": peak_rss_mib(), "backend": "opencv"}
    xp, sync, backend = device_xp()
    da, db, oa, ob = xp.asarray(a), xp.asarray(b), xp.asarray(octave_a), xp.asarray(octave_b)

    def allowed(rows: slice) -> Any:
        return same_value(oa[rows], ob)

    seconds = timed(lambda: match_descriptors(da, db, 0.8, False, allowed if masked else None), sync)
    return {"seconds": seconds, "peak_mib": peak_rss_mib(), "backend": backend}


def cases(large: bool) -> list[tuple[str, Any, tuple[Any, ...]]]:
    out: list[tuple[str, Any, tuple[Any, ...]]] = [
        (f"Harris {h}x{w}", harris_case, (h, w)) for h, w in ((2000, 2000), (8000, 8000), (1800, 75000))
    ]
    sift_sizes = ((600, 800), (1336, 2008), (2672, 4016)) if large else ((600, 800), (1336, 2008))
    out += [(f"SIFT {h}x{w}", sift_case, (h, w)) for h, w in sift_sizes]
    sizes = (1000, 10000, 20000) if large else (1000, 10000)
    for n in sizes:
        for dim in (128, 32):
            for masked in (False, True):
                out.append((f"match {n}x{n} {dim}-D{' masked' if masked else ''}", match_case, (n, dim, masked)))
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--large", action="store_true", help="also SIFT on 4016x2672 and 20k x 20k matching (slow on a CPU)"
    )
    parser.add_argument("--json", type=Path, default=None, help="also save the figures here")
    args = parser.parse_args(argv)
    rows = []
    print(f"{'case':30}{'ours s':>10}{'OpenCV s':>10}{'ratio':>8}{'ours MiB':>10}{'OpenCV MiB':>11}  backend")
    for name, fn, params in cases(args.large):
        ours, cv = in_child(fn, *params, "ours"), in_child(fn, *params, "opencv")
        ratio = ours["seconds"] / cv["seconds"]
        rows.append({"case": name, "ours": ours, "opencv": cv, "ratio_time": ratio})
        print(
            f"{name:30}{ours['seconds']:10.4f}{cv['seconds']:10.4f}{ratio:8.2f}"
            f"{ours['peak_mib']:10.0f}{cv['peak_mib']:11.0f}  {ours.get('backend', '?')}"
        )
    if all(r["ours"].get("backend") == "numpy" for r in rows):
        print("GPU rows: not measured (no CUDA device on this machine)")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
