"""Seam visibility and compose time: our multiband and feathered mosaics against OpenCV's stitcher (graph-cut
seams + multiband) over the same warped frames, each measured on its own cut lines the same way.

Run by hand from the repository root::

    .venv/bin/python bench/seams.py [DIR ...] [--working-max-px N] [--synthetic N] [--repeats 2] [--json OUT]

Data sets: each ``DIR`` given, else ``drone_brighton_strip1`` and ``stitching`` (budapest1-6) from
``../shared/data`` where present, and ``--synthetic N`` (default 8, 0 for none) frames of 1280 x 960 from
``tests/scenes.make_seam_flight`` (exposure +-20 %, a lens fall-off, a car that drives between shots).

For each set our pipeline runs once (``blend: multiband``; the synthetic flight with ``vignetting_correction``),
then ``compose_mosaic`` alone again ``--repeats`` times with each blend (the fastest run counts): its wall time,
the CPU seconds of its parts, and the seam visibility the stage reports (the mean colour step across the cut
lines over the same step 16 px beside them, 1.0: invisible; a feathered mosaic on the lines multiband cuts).

The reference is OpenCV's stitching pipeline from its detail API, as ``cv2.Stitcher`` (and OpenCV's
``stitching_detailed`` sample) compose, over our alignment: every working frame warped onto our output grid,
``BlocksGainCompensator`` fed at the seam scale (0.1 MP per frame, the stitcher's ``seam_est_resol``),
``GraphCutSeamFinder('COST_COLOR')`` there, the seam masks dilated, brought to full size and cut by each
warped frame's mask, then ``MultiBandBlender`` with the stitcher's band count (log2 of 5 % of the panorama's
diagonal size, minus 1). Its seam visibility is measured by the same function on its own cut lines (the owners
of its low-resolution seam masks); each mosaic is also measured on the other's lines. Ratios are ours / OpenCV.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"
DEFAULT_DIRS = [DATA / "drone_brighton_strip1", DATA / "stitching"]
sys.path.insert(0, str(ROOT))  # run as a script from a checkout, installed or not

from workers.algorithms.mosaic import output_box, seam_points, seam_visibility  # noqa: E402
from workers.pipeline import pipeline_key, process_directory, run_stage  # noqa: E402
from workers.raster_io import open_window_reader  # noqa: E402
from workers.workspace import JobWorkspace  # noqa: E402

SEAM_MEGAPIX = 0.1  # cv2.Stitcher's seam_est_resol
BLEND_STRENGTH = 5.0  # stitching_detailed's default: blend width is this % of the panorama's diagonal size


def compose_once(ws: JobWorkspace, blend: str) -> dict[str, Any]:
    """``compose_mosaic`` again with ``blend``: wall seconds, parts' CPU seconds, seam visibility."""
    cfg = ws.load_config()
    cfg["blend"] = blend
    cfg["measure_seams"] = True  # a feathered mosaic measured on the seams a multiband one would be cut along
    ws.save_config(cfg)
    started = time.perf_counter()
    report = run_stage(ws, pipeline_key("mosaic", cfg), "compose_mosaic", rerun=True)
    parts = sum(v["seconds"] for v in report["parts"]["by"].values())
    return {"seconds": time.perf_counter() - started, "part_seconds": parts, "visibility": report["seam_visibility"]}


def array_reader(rgb: np.ndarray, mask: np.ndarray) -> Any:
    """``read(x, y, w, h)`` over an in-memory mosaic, as ``open_window_reader`` reads a COG."""

    def read(x: int, y: int, w: int, h: int) -> tuple[np.ndarray, np.ndarray]:
        x0, y0, x1, y1 = max(x, 0), max(y, 0), min(x + w, mask.shape[1]), min(y + h, mask.shape[0])
        if x1 <= x0 or y1 <= y0:
            return np.zeros((0, 0, 3), np.uint8), np.zeros((0, 0), bool)
        return rgb[y0:y1, x0:x1], mask[y0:y1, x0:x1]

    return read


def opencv_mosaic(ws: JobWorkspace) -> dict[str, Any]:
    """OpenCV's gain compensation, graph-cut seams and multiband blending over our warped working frames, on
    our output grid. Returns its RGB, mask, seam labels (low resolution) and their scale, and seconds."""
    geo = ws.load_georef()
    frames = ws.load_composed_frames()
    homs = ws.load_alignment().homographies
    keys = sorted(homs)
    to_frame = {k: np.linalg.inv(homs[k]) @ geo.output_to_plane for k in keys}
    started = time.perf_counter()
    sizes = {k: (frames[k].width, frames[k].height) for k in keys}
    seam_scale = min(1.0, math.sqrt(SEAM_MEGAPIX * 1e6 / np.mean([w * h for w, h in sizes.values()])))
    full, low = [], []
    for k in keys:
        image = ws.load_compose_image(k)
        full.append(_warp(image, to_frame[k], sizes[k], 1.0, geo.width, geo.height))
        low.append(_warp(image, to_frame[k], sizes[k], seam_scale, geo.width, geo.height))
    compensator = cv2.detail.ExposureCompensator_createDefault(cv2.detail.ExposureCompensator_GAIN_BLOCKS)
    compensator.feed([c for c, _, _ in low], [im for _, im, _ in low], [cv2.UMat(m) for _, _, m in low])
    finder = cv2.detail_GraphCutSeamFinder("COST_COLOR")
    seams = finder.find([im.astype(np.float32) for _, im, _ in low], [c for c, _, _ in low],
                        [cv2.UMat(m) for _, _, m in low])  # fmt: skip
    seams = [np.asarray(cv2.UMat.get(s) if isinstance(s, cv2.UMat) else s) for s in seams]
    area = geo.width * geo.height
    bands = max(1, int(math.ceil(math.log2(math.sqrt(area) * BLEND_STRENGTH / 100.0)) - 1))
    blender = cv2.detail_MultiBandBlender(0, bands)
    blender.prepare((0, 0, geo.width, geo.height))
    for n, (corner, image, mask) in enumerate(full):
        image = compensator.apply(n, corner, image, mask)
        seam = cv2.dilate(seams[n], np.ones((3, 3), np.uint8))
        seam = cv2.resize(seam, (mask.shape[1], mask.shape[0]), interpolation=cv2.INTER_LINEAR_EXACT)
        blender.feed(image.astype(np.int16), cv2.bitwise_and(seam, mask), corner)
    pano, pano_mask = blender.blend(None, None)
    seconds = time.perf_counter() - started
    labels = _labels(keys, low, seams, geo.width, geo.height, seam_scale)
    rgb = np.clip(pano, 0, 255).astype(np.uint8)[..., ::-1]
    return {"rgb": rgb, "mask": pano_mask > 0, "labels": labels, "scale": seam_scale, "seconds": seconds,
            "bands": bands}  # fmt: skip


def _warp(
    image: np.ndarray, to_frame: np.ndarray, size: tuple[int, int], scale: float, width: int, height: int
) -> tuple[tuple[int, int], np.ndarray, np.ndarray]:
    """Frame warped onto the output grid at ``scale``, over its box: (corner, BGR uint8, mask uint8 255)."""
    x0, y0, x1, y1 = output_box(to_frame, size, width, height)
    c0, r0 = int(math.floor(x0 * scale)), int(math.floor(y0 * scale))
    c1, r1 = int(math.ceil(x1 * scale)), int(math.ceil(y1 * scale))
    # scaled grid pixel (c, r) centre -> output px (GDAL corners) ((c + 0.5) / scale) -> frame px
    to_out = np.array([[1 / scale, 0, (c0 + 0.5) / scale], [0, 1 / scale, (r0 + 0.5) / scale], [0, 0, 1]])
    M = to_frame @ to_out
    flags = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
    warped = cv2.warpPerspective(image, M, (c1 - c0, r1 - r0), flags=flags, borderMode=cv2.BORDER_REFLECT)
    inside = np.full(image.shape[:2], 255, np.uint8)
    mask = cv2.warpPerspective(inside, M, (c1 - c0, r1 - r0), flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP)
    return (c0, r0), warped, mask


def _labels(
    keys: list[int], low: list[Any], seams: list[np.ndarray], width: int, height: int, scale: float
) -> np.ndarray:
    """(h, w) int32 owner of each cell of the seam-scale grid: the frame whose seam mask holds it (-1: none)."""
    labels = np.full((int(math.ceil(height * scale)) + 1, int(math.ceil(width * scale)) + 1), -1, np.int32)
    for k, (corner, _, _), seam in zip(keys, low, seams, strict=True):
        c0, r0 = corner
        view = labels[r0 : r0 + seam.shape[0], c0 : c0 + seam.shape[1]]
        view[(seam[: view.shape[0], : view.shape[1]] > 0) & (view < 0)] = k
    return labels


def measure(name: str, src: Path, options: dict[str, Any], repeats: int) -> dict[str, Any]:
    print(f"{name}: our pipeline, then compose_mosaic x{repeats} per blend, then OpenCV's ...", flush=True)
    with tempfile.TemporaryDirectory() as tmp:
        ws = JobWorkspace(Path(tmp) / "job")
        process_directory(src, ws.root, {**options, "blend": "multiband"})
        runs: dict[str, list[dict[str, Any]]] = {"feather": [], "multiband": []}
        for _ in range(repeats):
            for blend in runs:
                runs[blend].append(compose_once(ws, blend))
        best = {blend: min(r, key=lambda v: v["seconds"]) for blend, r in runs.items()}
        ours_labels = ws.load_part_arrays("compose_mosaic")["labels"]
        ours_scale = float(ws.load_part_inputs("compose_mosaic")["label_scale"])
        cv = opencv_mosaic(ws)
        cv_read = array_reader(cv["rgb"], cv["mask"])
        with open_window_reader(ws.mosaic_path()) as ours_read:  # the multiband mosaic: composed last
            cross = {
                "ours_on_cv_seams": seam_visibility(ours_read, *seam_points(cv["labels"], cv["scale"])),
                "cv_on_our_seams": seam_visibility(cv_read, *seam_points(ours_labels, ours_scale)),
            }
        cv_vis = seam_visibility(cv_read, *seam_points(cv["labels"], cv["scale"]))
    return {
        "name": name,
        "multiband": best["multiband"],
        "feather": best["feather"],
        "opencv": {"seconds": cv["seconds"], "visibility": cv_vis, "bands": cv["bands"]},
        **cross,
    }


def print_table(results: list[dict[str, Any]]) -> None:
    head = (
        f"{'data set':22}{'vis mb':>8}{'vis fe':>8}{'vis cv':>8}{'mb/cv':>7}{'fe/cv':>7}{'mb@cv':>7}{'cv@mb':>7}"
        f"{'mb s':>7}{'fe s':>7}{'mb/fe':>7}{'mb cpu':>8}{'fe cpu':>8}{'cpu x':>7}{'cv s':>7}"
    )
    print(head)
    for r in results:
        mb, fe, cv = r["multiband"], r["feather"], r["opencv"]
        print(
            f"{r['name'][:21]:22}{mb['visibility']:>8.3f}{fe['visibility']:>8.3f}{cv['visibility']:>8.3f}"
            f"{mb['visibility'] / cv['visibility']:>7.2f}{fe['visibility'] / cv['visibility']:>7.2f}"
            f"{r['ours_on_cv_seams']:>7.3f}{r['cv_on_our_seams']:>7.3f}"
            f"{mb['seconds']:>7.2f}{fe['seconds']:>7.2f}{mb['seconds'] / fe['seconds']:>7.2f}"
            f"{mb['part_seconds']:>8.2f}{fe['part_seconds']:>8.2f}{mb['part_seconds'] / fe['part_seconds']:>7.2f}"
            f"{cv['seconds']:>7.2f}"
        )
    print(
        "vis: seam visibility (1.0 invisible) of our multiband (mb) and feathered (fe) mosaics on our cut lines and"
        " of OpenCV's (cv) on its own; mb@cv / cv@mb: each on the other's lines. s: compose_mosaic wall seconds"
        " (fastest run); cpu: its parts' seconds; cv s: OpenCV's compensation, seams and blend (no COG written)."
    )


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dirs", nargs="*", type=Path, help="folders of frames (default: the shared data sets)")
    parser.add_argument("--working-max-px", type=int, default=None, help="longest side of the working frames")
    parser.add_argument("--synthetic", type=int, default=8, help="frames of the synthetic seam flight (0: none)")
    parser.add_argument("--repeats", type=int, default=2, help="compose runs per blend; the fastest counts")
    parser.add_argument("--json", type=Path, default=None, help="also save the figures here")
    return parser.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    options: dict[str, Any] = {} if args.working_max_px is None else {"working_max_px": args.working_max_px}
    dirs = args.dirs or [d for d in DEFAULT_DIRS if d.is_dir()]
    results = [measure(d.name, d, options, args.repeats) for d in dirs]
    if args.synthetic:
        from tests.scenes import make_seam_flight

        with tempfile.TemporaryDirectory() as tmp:
            make_seam_flight(Path(tmp) / "frames", n_frames=args.synthetic, frame_size=(1280, 960))
            name = f"synthetic {args.synthetic} seam"
            results.append(measure(name, Path(tmp) / "frames", {**options, "vignetting_correction": True},
                                   args.repeats))  # fmt: skip
    print_table(results)
    if args.json:
        args.json.write_text(json.dumps(results, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
