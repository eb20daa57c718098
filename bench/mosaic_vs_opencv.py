"""Our mosaic pipeline against OpenCV's Stitcher (SCANS mode) on the same frames, at the same size.

Run by hand from the repository root::

    .venv/bin/python bench/mosaic_vs_opencv.py [DIR ...] [--working-max-px N] [--synthetic N]
        [--scaling 10 30 100] [--repeat N] [--json OUT]

Data sets: each ``DIR`` given, else ``drone_brighton_strip1`` and ``stitching`` (budapest1-6) from
``../shared/data`` where present; ``--synthetic N`` (default 30, 0 for none) adds a GPS flight of N frames
rendered by ``tests/scenes.py`` into a temp dir. ``--scaling`` times our pipeline alone on synthetic flights
of those sizes (seconds per frame should stay flat). ``--repeat N`` runs each side N times per data set,
alternately, and reports the medians (a single cold run varies by 10-20 % on a 2-core machine) with the ranges.

Each run happens in its own spawned child process, so the peak resident memory it reports (the child's VmHWM)
is that run's alone. A line per data set splits each side's peak into what its process held when the clock
started (its libraries and modules: ours import rasterio's GDAL and Pydantic, OpenCV's side only cv2 and NumPy)
and what the run added on top; another gives each side's CPU seconds (all its threads) and the cores it kept busy
on average (on c cores no wall time drops below CPU seconds / c). Both runs start from the same JPEGs, and both
clocks include decoding them: ours is asked for working copies of N px on the longest side, and OpenCV's run
resizes the decoded frames to N px (``cv2.INTER_AREA``) before it stitches them.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"
DEFAULT_DIRS = [DATA / "drone_brighton_strip1", DATA / "stitching"]
IMAGE_SUFFIXES = {".jpg", ".jpeg", ".png", ".tif", ".tiff"}
sys.path.insert(0, str(ROOT))  # run as a script from a checkout, installed or not


def peak_rss_mib() -> float:
    """This process's peak resident set size (VmHWM), MiB."""
    return _status_mib("VmHWM")


def rss_mib() -> float:
    """This process's resident set size now (VmRSS), MiB."""
    return _status_mib("VmRSS")


def cpu_seconds() -> float:
    """CPU time this process has used so far, user and system, all its threads (``os.times``)."""
    times = os.times()
    return times.user + times.system


def _status_mib(field: str) -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(f"{field}:"):
            return int(line.split()[1]) / 1024
    raise RuntimeError(f"no {field} in /proc/self/status (Linux only)")


def run_ours(src: str, working_max_px: int, extra: dict[str, Any] | None = None) -> dict[str, Any]:
    """Child: the full pipeline, including writing the COG and report.json into a temp dir.

    The stage modules are imported before the clock starts, as a worker imports its tasks once when it
    starts (about 0.4 s of rasterio, Pydantic and the stages); the OpenCV run likewise imports cv2 first. What
    the process holds then (``start_mib``) is in its peak, as OpenCV's and NumPy's libraries are in the other's.
    """
    from workers.pipeline import pipeline_key, process_directory, stage_function, stage_names

    options = {"working_max_px": working_max_px, **(extra or {})}
    for stage in stage_names(pipeline_key("mosaic", options)):
        stage_function(stage)
    start_mib = rss_mib()
    with tempfile.TemporaryDirectory() as out:
        started, cpu_started = time.perf_counter(), cpu_seconds()
        try:
            report = process_directory(Path(src), Path(out), options)
        except Exception as exc:  # a benchmark reports the failure instead of dying
            return {
                "ok": False,
                "status": f"{type(exc).__name__}: {exc}",
                "seconds": time.perf_counter() - started,
                "peak_mib": peak_rss_mib(),
                "start_mib": start_mib,
            }
        seconds, cpu_s = time.perf_counter() - started, cpu_seconds() - cpu_started
    used = report.get("frames_used")
    return {
        "ok": True,
        "status": "ok",
        "seconds": seconds,
        "cpu_s": cpu_s,
        "peak_mib": peak_rss_mib(),
        "start_mib": start_mib,
        "size": [report["mosaic"]["width"], report["mosaic"]["height"]],
        "frames_used": len(used) if isinstance(used, list) else used,  # the report lists them
        "tie_point_rms_px": report.get("tie_point_rms_px"),
        "tie_point_rms_px_original": report.get("tie_point_rms_px_original"),
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

    start_mib = rss_mib()
    started, cpu_started = time.perf_counter(), cpu_seconds()
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
        "cpu_s": cpu_seconds() - cpu_started,
        "peak_mib": peak_rss_mib(),
        "start_mib": start_mib,
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


def memory_split(ours: dict[str, Any], cv: dict[str, Any]) -> str | None:
    """Each side's peak as what its process held when the clock started (its libraries and modules) plus what
    the run added on top; None unless both runs succeeded."""
    if not (ours["ok"] and cv["ok"] and "start_mib" in ours and "start_mib" in cv):
        return None
    added = {who: r["peak_mib"] - r["start_mib"] for who, r in (("ours", ours), ("cv", cv))}
    ratio = f"{added['ours'] / added['cv']:.2f}x" if added["cv"] > 0 else "-"
    return (
        f"MiB at the start (imports) ours {ours['start_mib']:.0f}, OpenCV {cv['start_mib']:.0f}; added by the run "
        f"ours {added['ours']:.0f}, OpenCV {added['cv']:.0f} ({ratio})"
    )


def cpu_split(ours: dict[str, Any], cv: dict[str, Any]) -> str | None:
    """Each side's CPU seconds (all its threads) and the cores that kept busy on average (CPU / wall); None unless
    both runs succeeded. On a machine of few cores, CPU seconds are what a wall time can be cut to at best."""
    if not (ours["ok"] and cv["ok"] and "cpu_s" in ours and "cpu_s" in cv):
        return None
    return (
        f"CPU s ours {ours['cpu_s']:.2f}, OpenCV {cv['cpu_s']:.2f} ({ours['cpu_s'] / cv['cpu_s']:.2f}x); cores busy "
        f"on average ours {ours['cpu_s'] / ours['seconds']:.2f}, OpenCV {cv['cpu_s'] / cv['seconds']:.2f}"
    )


def _size(r: dict[str, Any]) -> str:
    return "x".join(map(str, r["size"])) if "size" in r else "-"


def print_table(results: list[dict[str, Any]]) -> None:
    """One row per data set: both runs' time, peak RSS, frames used and output size, and the ratios."""
    head = (
        f"{'data set':24}{'frames':>7}{'ours s':>8}{'cv s':>8}{'time x':>8}{'ours MiB':>9}{'cv MiB':>8}"
        f"{'mem x':>7}{'used ours/cv':>13}{'ours px':>12}{'cv px':>12}{'RMS px*':>8}"
    )
    print(head)
    for res in results:
        ours, cv = res["ours"], res["opencv"]
        r = {k: "-" if v is None else f"{v:.2f}" for k, v in ratios(ours, cv).items()}
        rms = ours.get("tie_point_rms_px_original")
        used = f"{ours.get('frames_used', '-')}/{cv.get('frames_used', '-')}"
        print(
            f"{res['name'][:23]:24}{res['frames']:>7}{ours['seconds']:>8.2f}{cv['seconds']:>8.2f}{r['seconds']:>8}"
            f"{ours['peak_mib']:>9.0f}{cv['peak_mib']:>8.0f}{r['peak_mib']:>7}{used:>13}"
            f"{_size(ours):>12}{_size(cv):>12}{'-' if rms is None else f'{rms:.2f}':>8}"
        )
    print("time x, mem x: ours / OpenCV in the same run. *our tie-point RMS in the photos' own pixels.")
    for res in results:
        runs = res.get("runs", {})
        if len(runs.get("ours", [])) > 1:  # --repeat: the medians above, the ranges here
            spread = {who: [r[0] for r in runs[who]] for who in ("ours", "opencv")}
            paired = [r["seconds"] for r in runs["ratios"] if r["seconds"] is not None]
            print(
                f"{res['name']}: {len(runs['ours'])} runs each, medians above; ours {min(spread['ours']):.2f}-"
                f"{max(spread['ours']):.2f} s, OpenCV {min(spread['opencv']):.2f}-{max(spread['opencv']):.2f} s"
                + (f", time x run by run {min(paired):.2f}-{max(paired):.2f}" if paired else "")
            )
    for res in results:
        if (line := memory_split(res["ours"], res["opencv"])) is not None:
            print(f"{res['name']}: {line}")
    for res in results:
        if (line := cpu_split(res["ours"], res["opencv"])) is not None:
            print(f"{res['name']}: {line}")
    for res in results:
        for who in ("ours", "opencv"):
            if not res[who]["ok"]:
                print(f"{res['name']}: {who} failed: {res[who]['status']}")
        stages = res["ours"].get("stage_seconds")
        if stages:
            print(f"{res['name']}: our stages, s: " + ", ".join(f"{k} {v:.2f}" for k, v in stages.items()))


def synthetic_flight(out: Path, n_frames: int) -> Path:
    """A GPS flight of ``n_frames`` 1280 x 960 frames, two serpentine lines, from tests/scenes.py."""
    from tests.scenes import make_flight

    make_flight(out, n_frames=n_frames, frame_size=(1280, 960), layout="grid", rotation_deg=6, gps=True, seed=7)
    return out


def measure(name: str, src: Path, working_max_px: int, with_opencv: bool = True, repeat: int = 1) -> dict[str, Any]:
    """Both runs on ``src``, ``repeat`` times each, alternately, each in a fresh child. ``ours`` and ``opencv`` are
    each side's run of median seconds (its peak memory the median of the runs'); ``runs`` every run's seconds and
    peak, and the ratios of each pair of runs."""
    n = len(image_paths(src))
    print(f"{name}: {n} frames, both runs at {working_max_px} px on the longest side ...", flush=True)
    ours_runs, cv_runs = [], []
    for _ in range(repeat):
        ours_runs.append(in_child(run_ours, str(src), working_max_px))
        cv_runs.append(in_child(run_opencv, str(src), working_max_px) if with_opencv else {"ok": False})
    for cv in cv_runs:
        cv.setdefault("status", "not run")
        cv.setdefault("seconds", float("nan"))
        cv.setdefault("peak_mib", float("nan"))
    ours, cv = median_run(ours_runs), median_run(cv_runs)
    return {
        "name": name,
        "dir": str(src),
        "frames": n,
        "working_max_px": working_max_px,
        "ours": ours,
        "opencv": cv,
        "ratios": ratios(ours, cv),
        "runs": {
            "ours": [[r["seconds"], r["peak_mib"]] for r in ours_runs],
            "opencv": [[r["seconds"], r["peak_mib"]] for r in cv_runs],
            "ratios": [ratios(a, b) for a, b in zip(ours_runs, cv_runs, strict=True)],
        },
    }


def median_run(runs: list[dict[str, Any]]) -> dict[str, Any]:
    """The run of median seconds (the lower middle one of an even count), with the medians of the runs' peaks
    and starting memory; a failed run, if any failed."""
    failed = [r for r in runs if not r["ok"]]
    if failed:
        return failed[0]
    middle = dict(sorted(runs, key=lambda r: r["seconds"])[(len(runs) - 1) // 2])
    for key in ("peak_mib", "start_mib", "cpu_s"):
        if all(key in r for r in runs):
            middle[key] = statistics.median(r[key] for r in runs)
    return middle


def native_cost(result: dict[str, Any]) -> dict[str, Any]:
    """Ours again on the same frames with ``output_resolution: native`` (composed from the full photos)."""
    native = in_child(run_ours, result["dir"], result["working_max_px"], {"output_resolution": "native"})
    return {
        "name": result["name"],
        "working_s": result["ours"]["seconds"],
        "native_s": native["seconds"],
        "peak_mib": native["peak_mib"],
        "size": _size(native),
    }


def print_scaling(rows: list[dict[str, Any]]) -> None:
    print(f"{'frames':>7}{'ours s':>9}{'s/frame':>9}{'peak MiB':>10}{'used':>6}")
    for row in rows:
        ours = row["ours"]
        print(
            f"{row['frames']:>7}{ours['seconds']:>9.2f}{ours['seconds'] / row['frames']:>9.3f}"
            f"{ours['peak_mib']:>10.0f}{str(ours.get('frames_used', '-')):>6}"
        )


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dirs", nargs="*", type=Path, help="folders of frames (default: the shared data sets)")
    parser.add_argument(
        "--working-max-px",
        type=int,
        default=None,
        help="longest side of the working frames, both runs (default: the pipeline's)",
    )
    parser.add_argument("--synthetic", type=int, default=30, help="frames of the synthetic GPS flight (0: none)")
    parser.add_argument("--scaling", type=int, nargs="*", default=[], help="synthetic flight sizes, ours only")
    parser.add_argument("--json", type=Path, default=None, help="also save the figures here")
    parser.add_argument(
        "--repeat", type=int, default=1, help="runs of each side per data set, alternately (medians reported)"
    )
    parser.add_argument(
        "--native", action="store_true", help="also time ours at the photos' own resolution (output_resolution)"
    )
    return parser.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    dirs = args.dirs or [d for d in DEFAULT_DIRS if d.is_dir()]
    for d in dirs:
        if not d.is_dir() or len(image_paths(d)) < 2:
            sys.exit(f"{d}: no folder with at least 2 images (the defaults need ../shared/data)")
    if args.working_max_px is None:
        from workers.config import MosaicConfig

        args.working_max_px = MosaicConfig().working_max_px
    print(
        "both clocks include decoding the JPEGs; OpenCV stitches them resized to the same size; a child process a run"
    )
    results = [measure(d.name, d, args.working_max_px, repeat=args.repeat) for d in dirs]
    scaling: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory() as tmp:
        if args.synthetic:
            src = synthetic_flight(Path(tmp) / f"synthetic{args.synthetic}", args.synthetic)
            results.append(measure(f"synthetic {args.synthetic} GPS", src, args.working_max_px, repeat=args.repeat))
        for n in args.scaling:
            src = synthetic_flight(Path(tmp) / f"scaling{n}", n)
            scaling.append(measure(f"synthetic {n}", src, args.working_max_px, with_opencv=False))
    print_table(results)
    if scaling:
        print_scaling(scaling)
    native = [native_cost(r) for r in results if args.native and Path(r["dir"]).is_dir()]
    if native:
        print(f"{'data set':24}{'working s':>10}{'native s':>10}{'time x':>8}{'native px':>14}{'native MiB':>11}")
        for row in native:
            print(
                f"{row['name'][:23]:24}{row['working_s']:>10.2f}{row['native_s']:>10.2f}"
                f"{row['native_s'] / row['working_s']:>8.2f}{row['size']:>14}{row['peak_mib']:>11.0f}"
            )
    if args.json:
        figures = {"working_max_px": args.working_max_px, "data_sets": results, "scaling": scaling, "native": native}
        args.json.write_text(json.dumps(figures, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
