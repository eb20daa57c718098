"""Aerial strips with known truth: a synthetic multi-lens strip through the whole pipeline, timed and checked.

Run by hand from the repository root::

    .venv/bin/python bench/strips.py [--frames 40] [--size 75000 1800] [--options '{"...": ...}'] [--keep DIR]
        [--processes N]

Frames are rendered by ``tests/strip_scenes.make_strip`` (JPEG-in-TIFF, CCD steps, vignetting, noisy GPS in a side
``gps.csv``; ``--render-processes`` at once) before the clock starts; with ``--keep DIR`` a strip rendered there
before with the same arguments is used again (its truth pickled beside it) and the job folder is replaced. The
pipeline then runs in a spawned child process (its own peak memory; with ``--processes N`` its stages' parts on N
worker processes of its own, whose memory the sampled peaks add in: resident sets summed, and proportional sets,
which count the pages the processes share once in all). Printed: stage times (and the rest, mostly the
upload check of every frame) and frames per hour, peak RSS, disk (input, outputs, the job folder's peak size
sampled while it ran), tie-point RMS, every frame corner's error against the truth after one similarity (ground px,
which are native px), the frame centres' absolute error in metres against the GPS noise / sqrt(frames) the issue
asks for, the mosaic's size, and two web-map tiles read back from the mosaic by rio-tiler: one at its coarsest zoom
(from the smallest overview) and one at its finest (full resolution), each with its time and the share of it
covered.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import multiprocessing as mp
import pickle
import shutil
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # run as a script from a checkout, installed or not

DEFAULT_OPTIONS = {
    "mode": "strip",
    "ccd_segments": 32,
}  # native output, tie points coarse to fine, the CCD joins undone


def status_mib(field: str, pid: int | str = "self") -> float:
    """A process's ``/proc/<pid>/status`` memory field (``VmHWM``: peak resident, ``VmRSS``: resident), MiB."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(f"{field}:"):
            return int(line.split()[1]) / 1024
    raise RuntimeError(f"no {field} in /proc/{pid}/status (Linux only)")


def peak_rss_mib() -> float:
    return status_mib("VmHWM")


def run_pipeline(src: str, out: str, options: dict[str, Any], processes: int = 1) -> dict[str, Any]:
    """Child: the whole pipeline; its report, wall time and peak memory (stages imported first, as a worker); its
    parts on ``processes`` worker processes when more than 1."""
    from workers.pipeline import pipeline_key, process_directory, stage_function, stage_names

    for stage in stage_names(pipeline_key("mosaic", options)):
        stage_function(stage)
    started = time.perf_counter()
    try:
        report = process_directory(Path(src), Path(out), options, processes=processes)
    except Exception as exc:  # a benchmark reports the failure instead of dying
        return {"ok": False, "status": f"{type(exc).__name__}: {exc}", "seconds": time.perf_counter() - started}
    return {"ok": True, "seconds": time.perf_counter() - started, "peak_mib": peak_rss_mib(), "report": report}


def _child(conn: Any, args: tuple[Any, ...]) -> None:
    conn.send(run_pipeline(*args))
    conn.close()


def in_child(*args: Any, watch: Path | None = None) -> dict[str, Any]:
    """Run :func:`run_pipeline` in a spawned child; with ``watch``, also the folder's peak size while it ran
    (``peak_job_bytes``, sampled every 2 s: the working files a stage deletes count while they exist)."""
    ctx = mp.get_context("spawn")
    recv, send = ctx.Pipe(duplex=False)
    proc = ctx.Process(target=_child, args=(send, args))
    peak = [0]
    # (seconds since start, the child's tree's resident, its PSS, its largest process's resident MiB)
    memory: list[tuple[float, float, float, float]] = []
    done = threading.Event()

    clock = time.perf_counter()

    def sample() -> None:
        while not done.wait(2.0):
            peak[0] = max(peak[0], folder_bytes(watch) if watch and watch.exists() else 0)
            pid = proc.pid or 0
            memory.append((time.perf_counter() - clock, resident_mib(pid), proportional_mib(pid), largest_mib(pid)))

    sampler = threading.Thread(target=sample, daemon=True)
    proc.start()
    sampler.start()
    send.close()
    try:
        result: dict[str, Any] = recv.recv()
        result["answered_at"] = time.perf_counter() - clock  # the pipeline's end, on the samples' clock
    except EOFError:
        result = {"ok": False, "status": f"child died, exit code {proc.exitcode}", "seconds": float("nan")}
    proc.join()
    done.set()
    sampler.join()
    if watch is not None and watch.exists():
        result["peak_job_bytes"] = max(peak[0], folder_bytes(watch))
    result["memory_samples"] = memory
    return result


def resident_mib(pid: int) -> float:
    """A live process's resident set (VmRSS) with its descendants' (the pipeline's part workers), MiB; 0 once it
    is gone (or a zombie, which has none). Pages the processes share (libraries, mapped files) count once in each."""
    return tree_mib(pid, rss_mib)


def rss_mib(pid: int) -> float:
    """One process's resident set (VmRSS), MiB; 0 once it is gone."""
    try:
        return status_mib("VmRSS", pid)
    except (FileNotFoundError, RuntimeError):
        return 0.0


def proportional_mib(pid: int) -> float:
    """A live process's proportional set (``Pss`` of ``/proc/<pid>/smaps_rollup``: each page it shares with n
    processes counted 1/n) with its descendants', MiB: the host memory the process tree holds."""

    def own(p: int) -> float:
        try:
            text = Path(f"/proc/{p}/smaps_rollup").read_text()
        except (FileNotFoundError, ProcessLookupError, PermissionError):
            return 0.0
        return next((int(line.split()[1]) / 1024 for line in text.splitlines() if line.startswith("Pss:")), 0.0)

    return tree_mib(pid, own)


def largest_mib(pid: int) -> float:
    """The largest resident set (VmRSS) of a live process and its descendants, MiB: with part workers, one worker's
    share (a GPU context's host memory shows here) against the pipeline's process."""

    def tree(p: int) -> list[float]:
        return [rss_mib(p), *(m for child in children(p) for m in tree(child))]

    return max(tree(pid))


def tree_mib(pid: int, own: Callable[[int], float]) -> float:
    """``own(pid)`` summed over a process and its descendants (none once it is gone)."""
    return own(pid) + sum(tree_mib(child, own) for child in children(pid))


def children(pid: int) -> list[int]:
    """A process's child processes (``/proc/<pid>/task/*/children``)."""
    found = []
    for task in Path(f"/proc/{pid}/task").glob("*"):
        try:
            found += [int(c) for c in (task / "children").read_text().split()]
        except (FileNotFoundError, ProcessLookupError, ValueError):
            continue
    return found


def peak_by_stage(
    samples: list[tuple[float, float, float, float]], stage_seconds: dict[str, float], end: float
) -> dict[str, int]:
    """Each stage's peak resident MiB from the samples, the stages placed end to end back from ``end``, when the
    pipeline answered (what it spends outside its stages falls before the first)."""
    ends = {}
    for name, seconds in reversed(list(stage_seconds.items())):
        ends[name] = (end - seconds, end)
        end -= seconds
    return {
        name: round(max((mib for t, mib, *_ in samples if start <= t <= stop), default=0.0))
        for name, (start, stop) in reversed(list(ends.items()))
    }


def truth_errors(strip: Any, job: Path) -> dict[str, float]:
    """Corner errors (ground px) after one similarity; frame centres' and corners' absolute errors (m), and the
    corners' standard errors the adjustment predicted (``corner_sigma_*``, m: its worst corner per frame)."""
    from workers.algorithms.geometry import fit_similarity
    from workers.algorithms.mosaic import apply_homography, frame_corners
    from workers.workspace import JobWorkspace

    ws = JobWorkspace(job)
    align, geo, frames = ws.load_alignment(), ws.load_georef(), {f.index: f for f in ws.load_frames()}
    predicted, truth, centres, true_centres = [], [], [], []
    for k, H in sorted(align.homographies.items()):
        f = frames[k]
        predicted.append(apply_homography(H, frame_corners(f.width, f.height)))
        truth.append(apply_homography(strip.homographies[k], frame_corners(f.orig_width, f.orig_height)))
        centres.append(apply_homography(H, np.array([[(f.width - 1) / 2, (f.height - 1) / 2]]))[0])
        true_centres.append(strip.frame_center_utm(k))
    p, t = np.concatenate(predicted), np.concatenate(truth)
    S = fit_similarity(p, t)
    corner = np.linalg.norm(apply_homography(S, p) - t, axis=1)
    out = {"corner_max_px": float(corner.max()), "corner_rms_px": float(np.sqrt(np.mean(corner**2)))}
    if geo.georeferenced:
        utm = apply_homography(geo.plane_to_map, np.array(centres))
        absolute = np.linalg.norm(utm - np.array(true_centres), axis=1)
        out.update(centre_abs_max_m=float(absolute.max()), centre_abs_rms_m=float(np.sqrt(np.mean(absolute**2))))
        # the strip's mean position: what GPS noise / sqrt(frames) bounds (per axis), beside each centre's own miss
        mean_miss = np.mean(utm - np.array(true_centres), axis=0)
        out.update(centre_mean_miss_m=[float(v) for v in mean_miss])
        misses = np.linalg.norm(
            apply_homography(geo.plane_to_map, p) - apply_homography(strip.texture_to_utm, t), axis=1
        )
        out.update(corner_abs_max_m=float(misses.max()), corner_abs_rms_m=float(np.sqrt(np.mean(misses**2))))
        if align.corner_sigma_px:
            metres = np.sqrt(abs(np.linalg.det(geo.plane_to_map[:2, :2]))) * np.array(
                list(align.corner_sigma_px.values())
            )
            out.update(corner_sigma_max_m=float(metres.max()), corner_sigma_rms_m=float(np.sqrt(np.mean(metres**2))))
    return out


def ccd_error(strip: Any, report: dict[str, Any]) -> float | None:
    """The CCD steps' mean error over their mean size (log brightness), as compose_mosaic found them; None when
    the job did not look for them."""
    found = report.get("ccd_gains")
    if not found or len(found) != len(strip.ccd_gains):
        return None
    truth = np.diff(np.log(strip.ccd_gains))
    return float(np.abs(np.diff(np.log(found)) - truth).mean() / np.abs(truth).mean())


def show(figures: dict[str, Any]) -> None:
    """One figure a line: its name, then its value (floats to 4 significant digits)."""
    for key, value in figures.items():
        print(f"{key:32} {value:.4g}" if isinstance(value, float) else f"{key:32} {value}")


def tiles_read_back(mosaic: Path) -> dict[str, float]:
    """rio-tiler's 256 px tiles at the mosaic's centre at its coarsest and finest zooms: seconds and the share of
    pixels covered (each tile opens the COG afresh, as a tile server's request does)."""
    from rio_tiler.constants import WGS84_CRS
    from rio_tiler.io import Reader

    out: dict[str, float] = {}
    with Reader(str(mosaic)) as cog:
        west, south, east, north = cog.get_geographic_bounds(WGS84_CRS)
        zooms = {"min": cog.minzoom, "max": cog.maxzoom}
        out["overview_levels"] = len(cog.info().overviews or [])
    for name, zoom in zooms.items():
        started = time.perf_counter()
        with Reader(str(mosaic)) as cog:
            tile = cog.tms.tile((west + east) / 2, (south + north) / 2, zoom)
            image = cog.tile(tile.x, tile.y, zoom)
        out[f"tile_{name}_zoom"] = zoom
        out[f"tile_{name}_s"] = time.perf_counter() - started
        out[f"tile_{name}_covered"] = float(image.mask.mean() / 255)
    return out


def render(args: argparse.Namespace, root: Path) -> Any:
    """The strip the arguments ask for: rendered into ``root / "frames"``, or, when ``root`` holds one rendered
    with the same arguments (``strip.pickle``), that one."""
    from tests.strip_scenes import make_strip

    key = {"frames": args.frames, "size": list(args.size), "overlap": args.overlap, "gps_noise_m": args.gps_noise_m}
    saved = root / "strip.pickle"
    if saved.exists():
        with saved.open("rb") as f:
            kept_key, strip = pickle.load(f)
        if kept_key == key and all(path.exists() for path in strip.paths):
            print(f"using the {args.frames} frames rendered in {root / 'frames'}")
            return strip
    saved.unlink(missing_ok=True)
    started = time.perf_counter()
    strip = make_strip(
        root / "frames",
        args.frames,
        tuple(args.size),
        overlap=args.overlap,
        gps_noise_m=args.gps_noise_m,
        processes=args.render_processes,
    )
    with saved.open("wb") as f:
        pickle.dump((key, strip), f)
    print(f"rendered {args.frames} frames of {args.size[0]}x{args.size[1]} in {time.perf_counter() - started:.0f} s")
    return strip


def folder_bytes(folder: Path) -> int:
    total = 0
    for path in folder.rglob("*"):
        with contextlib.suppress(FileNotFoundError):  # a stage's working file deleted while it was counted
            total += path.stat().st_size if path.is_file() else 0
    return total


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=40)
    parser.add_argument("--size", type=int, nargs=2, default=(75000, 1800), metavar=("WIDTH", "HEIGHT"))
    parser.add_argument("--overlap", type=float, default=0.55)
    parser.add_argument("--gps-noise-m", type=float, default=1.0)
    parser.add_argument("--options", type=json.loads, default={}, help="job options over the strip defaults")
    parser.add_argument("--keep", type=Path, default=None, help="keep frames and job here (default: a temp dir)")
    parser.add_argument("--json", type=Path, default=None, help="also save the figures here")
    parser.add_argument("--render-processes", type=int, default=2, help="frames rendered at once")
    parser.add_argument(
        "--processes", type=int, default=1, help="the pipeline's parts on this many worker processes (1: threads)"
    )
    args = parser.parse_args(argv)
    from workers.workspace import JobWorkspace

    root = args.keep or Path(tempfile.mkdtemp(prefix="strips-"))
    try:
        root.mkdir(parents=True, exist_ok=True)
        strip = render(args, root)
        shutil.rmtree(root / "job", ignore_errors=True)
        options = {**DEFAULT_OPTIONS, **args.options}
        result = in_child(str(root / "frames"), str(root / "job"), options, args.processes, watch=root / "job")
        if not result["ok"]:
            print(f"pipeline failed after {result['seconds']:.1f} s: {result['status']}")
            return 1
        report = result["report"]
        input_bytes = folder_bytes(root / "frames")
        output_bytes = sum(path.stat().st_size for path in JobWorkspace(root / "job").outputs().values())
        figures: dict[str, Any] = {
            "frames": args.frames,
            "size": list(args.size),
            "options": options,
            "frames_used": len(report["frames_used"]),
            "seconds": result["seconds"],
            "frames_per_hour": 3600 * args.frames / result["seconds"],
            "peak_mib": result["peak_mib"],  # the pipeline's process; with part workers, the samples' peak too:
            "peak_sampled_mib": round(max((mib for _, mib, *_ in result["memory_samples"]), default=0.0)),
            # the same samples' proportional set: shared pages (libraries, mapped files) counted once in all
            "peak_pss_mib": round(max((pss for _, _, pss, _ in result["memory_samples"]), default=0.0)),
            "peak_process_mib": round(max((one for *_, one in result["memory_samples"]), default=0.0)),
            "processes": args.processes,
            "peak_mib_by_stage": peak_by_stage(
                result["memory_samples"], report["stage_seconds"], result["answered_at"]
            ),
            "input_bytes": input_bytes,
            "output_bytes": output_bytes,
            "peak_job_bytes": result["peak_job_bytes"],
            # the disk goal: input + everything the job held at its peak <= 1.2 x (input + outputs)
            "disk_over_input_output": (input_bytes + result["peak_job_bytes"]) / (input_bytes + output_bytes),
            "mosaic_px": report["mosaic"]["width"] * report["mosaic"]["height"],
            "tie_point_rms_px": report["tie_point_rms_px"],
            "tie_point_rms_px_original": report["tie_point_rms_px_original"],
            "gps_residual_rms_m": report["gps_residual_rms_m"],
            "gps_drift_m": report["gps_drift_m"],
            "stage_seconds": report["stage_seconds"],
            # the rest of the run: mostly the upload check of every frame (process_directory's inspect_image)
            "outside_stages_s": result["seconds"] - sum(report["stage_seconds"].values()),
            # the parted stages' serial plan and finish against their parts (which more processes shorten)
            **{
                f"{stage}_phases_s": (JobWorkspace(root / "job").load_stage_report(stage) or {}).get("phase_seconds")
                for stage in ("match_strips", "compose_mosaic")
            },
            "gps_noise_over_sqrt_frames_m": args.gps_noise_m / np.sqrt(args.frames),
            # what a similarity (4 parameters) fitted to n fixes of sigma per axis puts centres within, RMS over
            # the fixes: sigma sqrt(trace(hat) / n) = 2 sigma / sqrt(n), twice the figure above
            "centre_abs_floor_rms_m": 2 * args.gps_noise_m / np.sqrt(args.frames),
            **truth_errors(strip, root / "job"),
            "ccd_step_error": ccd_error(strip, JobWorkspace(root / "job").load_stage_report("compose_mosaic") or {}),
        }
        show(figures)
        try:  # printed last: a rio-tiler that cannot be imported (the GPU machine's own packages) loses nothing else
            tiles: dict[str, Any] = tiles_read_back(JobWorkspace(root / "job").mosaic_path())
        except Exception as exc:  # noqa: BLE001 - reported as a figure
            tiles = {"tiles_error": f"{type(exc).__name__}: {exc}"}
        figures.update(tiles)
        show(tiles)
        if args.json:
            args.json.write_text(json.dumps(figures, indent=2) + "\n")
    finally:
        if args.keep is None:
            shutil.rmtree(root, ignore_errors=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
