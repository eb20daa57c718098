"""Disparity maps on the Middlebury pairs and a DSM of a synthetic RPC pair: OpenCV's StereoSGBM (the
issue's reference settings) against our ``sgbm`` and ``local`` matchers, in the same run.

Run by hand from the repository root::

    .venv/bin/python bench/stereo.py [--data ../shared/data/stereo_middlebury] [--repeats 3] [--rpc-size 600]

For every Middlebury pair it prints the dense bad-pixel rate (error > 1 px or no value, over ground-truth
pixels, non-occluded where the set has a mask), the rate over valued pixels only, the density, the
ratio of the dense rate to the reference's, and seconds per megapixel (median of ``--repeats`` runs
after one warm-up). ``local`` runs on NumPy, and again on CuPy where a CUDA device is present.

Then the RPC pair of ``tests/stereo_scenes.make_rpc_pair`` (``--rpc-size`` px square, 1 m GSD, 40 m of
relief, 15 degree views): rectified through its RPCs once, each method's disparity triangulated and gridded
as the stereo DEM job does (the reference's holes left empty, ours filled and flagged), and scored against
the terrain: median error of the measured cells, completeness (ground cells seen by both views measured
within 1 GSD), and the matcher's seconds per megapixel.
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
    Method,
    StereoPair,
    local,
    match_pair,
    opencv_sgbm,
    read_pair,
    score_disparity,
    sgbm,
)
from workers.algorithms.geometry import lonlat_to_utm  # noqa: E402
from workers.algorithms.stereo import (  # noqa: E402
    grid_dsm,
    height_disparity_range,
    rpc_correspondences,
    rpc_rectification,
    to_8bit_pair,
    triangulate_rpc,
    warp_pair,
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


def bench_rpc_pair(size: int, repeats: int) -> None:
    """The DSM of a synthetic RPC pair from each method's disparities, scored against its terrain."""
    import tempfile  # noqa: PLC0415

    import rasterio  # noqa: PLC0415

    from tests.stereo_scenes import dsm_accuracy, make_rpc_pair  # noqa: PLC0415
    from workers.raster_io import write_array_cog  # noqa: PLC0415

    with tempfile.TemporaryDirectory() as folder:
        root = Path(folder)
        pair = make_rpc_pair(root / "pair", size=(size, size))
        images = [rasterio.open(p).read(1) for p in (pair.left, pair.right)]
        left, right = to_8bit_pair(images[0], images[1])
        corr = rpc_correspondences(*pair.rpcs, (size, size), pair.rpcs[0].height_range)
        rect = rpc_rectification(corr, (size, size))
        a, b, valid_a, valid_b = warp_pair(rect, left, right)
        low, count = height_disparity_range(corr, rect)
        print(
            f"\nRPC pair {size}x{size} px, {pair.gsd_m:g} m GSD: rectified {rect.width}x{rect.height}, "
            f"rows within {rect.residual_px:.3f} px, disparities {low}..{low + count}"
        )
        print(f"{'method':26s} {'median err':>10s} {'complete':>9s} {'x ref':>6s} {'s/MP':>7s}")
        calls: dict[str, Callable[[], tuple[np.ndarray, np.ndarray]]] = {
            "opencv-sgbm (reference)": lambda: _reference(a, b, valid_a, low, count),
            "sgbm": lambda: _ours(a, b, valid_a, valid_b, "sgbm", low, count),
            "local cpu": lambda: _ours(a, b, valid_a, valid_b, "local", low, count),
        }
        reference = None
        for name, call in calls.items():
            dense, filled = call()
            t = seconds(call, repeats) / (rect.width * rect.height / 1e6)
            rows, cols = np.nonzero(np.isfinite(dense))
            lon, lat, h, _ = triangulate_rpc(
                *pair.rpcs, corr, rect, cols.astype(float), rows.astype(float), dense[rows, cols]
            )
            east_north = lonlat_to_utm(np.column_stack([lon, lat]), pair.epsg)
            dsm = grid_dsm(east_north[:, 0], east_north[:, 1], h, ~filled[rows, cols], 1.0, pair.epsg)
            write_array_cog(root / "dsm.tif", dsm.height, transform=dsm.transform, epsg=dsm.epsg, nodata=-9999.0)
            write_array_cog(root / "mask.tif", dsm.state, transform=dsm.transform, epsg=dsm.epsg)
            score = dsm_accuracy(pair, root / "dsm.tif", root / "mask.tif")
            reference = score.median_error_m if reference is None else reference
            print(
                f"{name:26s} {score.median_error_m:9.3f}m {100 * score.completeness:8.1f}% "
                f"{score.median_error_m / reference:6.2f} {t:7.2f}"
            )


def _reference(a: np.ndarray, b: np.ndarray, valid: np.ndarray, low: int, count: int) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV's StereoSGBM as it comes: its holes stay holes (nothing is filled)."""
    dense = opencv_sgbm(a, b, count, low, params=REFERENCE)
    dense[~valid] = np.nan
    return dense, np.zeros(dense.shape, bool)


def _ours(
    a: np.ndarray, b: np.ndarray, valid_a: np.ndarray, valid_b: np.ndarray, method: Method, low: int, count: int
) -> tuple[np.ndarray, np.ndarray]:
    result = match_pair(a, b, method, low, count, valid_left=valid_a, valid_right=valid_b)
    return result.dense, result.filled


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=ROOT.parent / "shared" / "data" / "stereo_middlebury")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--rpc-size", type=int, default=600, help="side of the synthetic RPC pair's photos, px")
    args = parser.parse_args()
    folders = sorted(p for p in args.data.iterdir() if p.is_dir()) if args.data.is_dir() else []
    if not folders:
        sys.exit(f"no Middlebury pairs under {args.data}")
    print(f"CUDA device: {cuda_available()}; {NUM_DISPARITIES} disparities")
    for folder in folders:
        bench_pair(read_pair(folder), args.repeats)
    bench_rpc_pair(args.rpc_size, args.repeats)


if __name__ == "__main__":
    main()
