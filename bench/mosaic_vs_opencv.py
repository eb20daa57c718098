"""Our mosaic pipeline against OpenCV's Stitcher (SCANS mode) on the same frames, at the same size.

Run by hand from the repository root::

    .venv/bin/python bench/mosaic_vs_opencv.py [DIR] [--working-max-px N] [--json OUT]

Each run happens in its own spawned child process, so the peak resident memory it reports (the
child's VmHWM) is that run's alone. Both runs start from the same JPEGs: ours is asked for working
copies of N px on the longest side, and OpenCV gets the frames already resized to N px.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_DIR = ROOT.parent / "shared" / "data" / "drone_brighton_strip1"
IMAGE_SUFFIXES = {".jpg", ".jpeg", ".png", ".tif", ".tiff"}
sys.path.insert(0, str(ROOT))  # run as a script from a checkout, installed or not


def peak_rss_mib() -> float:
    """This process's peak resident set size (VmHWM), MiB."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    raise RuntimeError("no VmHWM in /proc/self/status (Linux only)")


def run_ours(src: str, working_max_px: int) -> dict[str, Any]:
    """Child: the full pipeline, including writing the COG and report.json into a temp dir."""
    from workers.pipeline import process_directory

    with tempfile.TemporaryDirectory() as out:
        started = time.perf_counter()
        try:
            report = process_directory(Path(src), Path(out), {"working_max_px": working_max_px})
        except Exception as exc:  # a benchmark reports the failure instead of dying
            return {
                "ok": False,
                "status": f"{type(exc).__name__}: {exc}",
                "seconds": time.perf_counter() - started,
                "peak_mib": peak_rss_mib(),
            }
        seconds = time.perf_counter() - started
    used = report.get("frames_used")
    return {
        "ok": True,
        "status": "ok",
        "seconds": seconds,
        "peak_mib": peak_rss_mib(),
        "size": [report["mosaic"]["width"], report["mosaic"]["height"]],
        "frames_used": len(used) if isinstance(used, list) else used,  # the report lists them
        "tie_point_rms_px": report.get("tie_point_rms_px"),
        "stage_seconds": report.get("stage_seconds"),
    }


def load_resized(path: Path, max_px: int) -> Any:
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    scale = min(1.0, max_px / max(img.shape[:2]))
    size = (round(img.shape[1] * scale), round(img.shape[0] * scale))
    return cv2.resize(img, size, interpolation=cv2.INTER_AREA) if scale < 1.0 else img


STITCH_STATUS = {0: "OK", 1: "ERR_NEED_MORE_IMGS", 2: "ERR_HOMOGRAPHY_EST_FAIL", 3: "ERR_CAMERA_PARAMS_ADJUST_FAIL"}


def run_opencv(src: str, working_max_px: int) -> dict[str, Any]:
    """Child: load, resize, stitch (SCANS, OpenCV's defaults otherwise) and write a TIFF."""
    import cv2

    started = time.perf_counter()
    frames = [load_resized(p, working_max_px) for p in image_paths(Path(src))]
    stitcher = cv2.Stitcher_create(cv2.Stitcher_SCANS)
    status, pano = stitcher.stitch(frames)
    ok = status == cv2.Stitcher_OK
    if ok:
        with tempfile.TemporaryDirectory() as out:
            cv2.imwrite(str(Path(out) / "pano.tif"), pano)
    result = {
        "ok": ok,
        "status": f"{status} {STITCH_STATUS.get(status, '')}",
        "seconds": time.perf_counter() - started,
        "peak_mib": peak_rss_mib(),
    }
    if ok:
        result.update(size=[pano.shape[1], pano.shape[0]], frames_used=len(stitcher.component()))
    return result


def image_paths(src: Path) -> list[Path]:
    return sorted(p for p in src.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)


def _child(conn: Any, fn: Any, args: tuple[Any, ...]) -> None:
    conn.send(fn(*args))
    conn.close()


def in_child(fn: Any, *args: Any) -> dict[str, Any]:
    """Run ``fn(*args)`` in a fresh spawned process (its own peak memory) and return its result.

    A plain Process rather than a Pool: pool workers are daemons and could not start processes.
    """
    ctx = mp.get_context("spawn")
    recv, send = ctx.Pipe(duplex=False)
    proc = ctx.Process(target=_child, args=(send, fn, args))
    proc.start()
    send.close()
    try:
        result = recv.recv()
    except EOFError:  # killed (out of memory?) before it could answer
        proc.join()
        return {
            "ok": False,
            "status": f"child died, exit code {proc.exitcode}",
            "seconds": float("nan"),
            "peak_mib": float("nan"),
        }
    proc.join()
    return result


def ratios(ours: dict[str, Any], cv: dict[str, Any]) -> dict[str, float | None]:
    """ours/OpenCV for time and memory; None unless both runs succeeded."""
    both = ours["ok"] and cv["ok"]
    return {k: round(ours[k] / cv[k], 3) if both else None for k in ("seconds", "peak_mib")}


def print_table(ours: dict[str, Any], cv: dict[str, Any]) -> None:
    def size(r: dict[str, Any]) -> str:
        return "x".join(map(str, r["size"])) if "size" in r else "-"

    r = {k: "-" if v is None else f"{v:.2f}" for k, v in ratios(ours, cv).items()}
    rows = [
        ("wall time, s", f"{ours['seconds']:.2f}", f"{cv['seconds']:.2f}", r["seconds"]),
        ("peak RSS, MiB", f"{ours['peak_mib']:.0f}", f"{cv['peak_mib']:.0f}", r["peak_mib"]),
        ("output size, px", size(ours), size(cv), ""),
        ("frames used", str(ours.get("frames_used", "-")), str(cv.get("frames_used", "-")), ""),
        ("status", ours["status"][:20], cv["status"][:20], ""),
    ]
    print(f"{'':18}{'ours':>22}{'OpenCV':>22}{'ours/OpenCV':>14}")
    for name, a, b, q in rows:
        print(f"{name:18}{a:>22}{b:>22}{q:>14}")
    rms = ours.get("tie_point_rms_px")
    print(f"our tie-point RMS: {'-' if rms is None else f'{rms:.3f}'} px (working resolution)")
    if ours["ok"] and cv["ok"] and ours["frames_used"] != cv["frames_used"]:
        print("note: the runs kept different numbers of frames, so they did different amounts of work")
    for who, res in (("ours", ours), ("OpenCV", cv)):
        if not res["ok"]:
            print(f"{who} failed: {res['status']}")


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dir", nargs="?", type=Path, default=DEFAULT_DIR, help="folder of frames")
    parser.add_argument(
        "--working-max-px",
        type=int,
        default=None,
        help="longest side of the working frames, both runs (default: the pipeline's)",
    )
    parser.add_argument("--json", type=Path, default=None, help="also save the figures here")
    return parser.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    if not args.dir.is_dir() or len(image_paths(args.dir)) < 2:
        sys.exit(f"{args.dir}: no folder with at least 2 images (the default needs ../shared/data)")
    if args.working_max_px is None:
        from workers.config import MosaicConfig

        args.working_max_px = MosaicConfig().working_max_px
    n = len(image_paths(args.dir))
    print(
        f"{n} frames from {args.dir}, both runs at {args.working_max_px} px on the longest side "
        "(OpenCV gets frames resized beforehand: same input, fair comparison); one child process each"
    )
    ours = in_child(run_ours, str(args.dir), args.working_max_px)
    cv = in_child(run_opencv, str(args.dir), args.working_max_px)
    print_table(ours, cv)
    if args.json:
        figures = {
            "dir": str(args.dir),
            "frames": n,
            "working_max_px": args.working_max_px,
            "ours": ours,
            "opencv": cv,
            "ratios_ours_over_opencv": ratios(ours, cv),
        }
        args.json.write_text(json.dumps(figures, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
