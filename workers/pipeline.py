"""The ordered stages of each job kind, how a job becomes a Celery chain, and the in-process runner.

Stage modules are imported lazily so that the API (which only needs names and weights) never loads
OpenCV or the stage code.
"""

from __future__ import annotations

import importlib
import os
import socket
import time
from collections.abc import Callable, Iterator
from concurrent.futures import Executor, ProcessPoolExecutor, ThreadPoolExecutor, as_completed, wait
from concurrent.futures.process import BrokenProcessPool
from contextlib import AbstractContextManager, contextmanager
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType
from typing import Any

from core.kinds import JobKind
from workers.algorithms.geometry import Camera
from workers.config import build_config
from workers.parallel import ordered_map, release_freed_memory, thread_count
from workers.tiff_jpeg import BLOCK_CACHE
from workers.workspace import JobWorkspace, ProgressFn, noop_progress


@dataclass(frozen=True)
class StageSpec:
    name: str  # also the module under workers.stages and the Celery task name suffix
    weight: float  # share of the job's progress bar, relative to the other stages
    # done in parts (its module has plan / run_part / finish, see run_parted), which Celery spreads over every
    # worker of the job's queue; a stage without parts runs whole in one task
    parted: bool = False
    gpu: bool = False  # its parts use gpu_kernels: sent to a GPU worker's queue when one is running


# A pipeline is a job kind, or a kind and the option that changes its stages ("mosaic.ortho").
PIPELINES: dict[str, tuple[StageSpec, ...]] = {
    JobKind.mosaic: (
        StageSpec("load_images", 10, parted=True),
        StageSpec("detect_features", 15, parted=True, gpu=True),
        StageSpec("match_features", 15, parted=True, gpu=True),
        StageSpec("measure_ties", 15, parted=True),
        StageSpec("align_frames", 10),
        StageSpec("georeference", 2),
        StageSpec("compose_mosaic", 30, parted=True),
        StageSpec("write_report", 3),
    ),
    f"{JobKind.mosaic}.ortho": (
        StageSpec("load_images", 10, parted=True),
        StageSpec("detect_features", 20, parted=True, gpu=True),
        StageSpec("match_features", 25, parted=True, gpu=True),
        StageSpec("adjust_bundle", 15),
        StageSpec("orthorectify_frames", 5),
        StageSpec("compose_mosaic", 30, parted=True),
        StageSpec("write_report", 3),
    ),
    f"{JobKind.mosaic}.strip": (
        StageSpec("load_images", 15, parted=True),
        StageSpec("match_strips", 35, parted=True, gpu=True),
        StageSpec("align_frames", 5),
        StageSpec("georeference", 2),
        StageSpec("compose_mosaic", 40, parted=True),
        StageSpec("write_report", 3),
    ),
    JobKind.calibration: (StageSpec("detect_corners", 60), StageSpec("calibrate_camera", 40)),
    f"{JobKind.calibration}.plumb_line": (StageSpec("fit_plumb_line", 100),),
    JobKind.stereo_calibration: (StageSpec("detect_corners", 60), StageSpec("calibrate_stereo", 40)),
    JobKind.crack_survey: (
        StageSpec("orient_camera", 5),
        StageSpec("rectify_specimen", 15),
        StageSpec("detect_cracks", 50),
        StageSpec("measure_cracks", 15),
        StageSpec("compare_stages", 5),
        StageSpec("write_crack_report", 10),
    ),
    JobKind.stereo_dem: (
        StageSpec("rectify_pair", 15),
        StageSpec("compute_disparity", 50),
        StageSpec("build_dsm", 30),
        StageSpec("write_stereo_report", 5),
    ),
}
PARTED_STAGES = {spec.name for specs in PIPELINES.values() for spec in specs if spec.parted}
# The option of a kind that selects a variant pipeline, and its default.
VARIANT_OPTIONS: dict[str, tuple[str, str]] = {
    JobKind.mosaic: ("mode", "planar"),
    JobKind.calibration: ("method", "chessboard"),
}


class PipelineError(Exception):
    """A stage cannot go on; the message tells the user what is wrong with their data or options."""


def option_camera(data: dict[str, Any] | None, option: str) -> Camera:
    """The camera a job's option ``option`` holds (camera JSON); a bad one is the user's to fix."""
    try:
        return Camera.from_json(data or {})
    except ValueError as exc:
        raise PipelineError(f"options.{option}: {exc}") from None


def pipeline_key(kind: str, options: dict[str, Any] | None) -> str:
    """The pipeline that runs a job of ``kind`` with ``options`` (as requested, defaults not merged)."""
    option, default = VARIANT_OPTIONS.get(kind, ("", ""))
    variant = f"{kind}.{(options or {}).get(option, default)}" if option else kind
    return variant if variant in PIPELINES else kind


def job_kind(pipeline: str) -> str:
    """The job kind (and so the config model) of a pipeline."""
    return pipeline.split(".", 1)[0]


def stage_names(pipeline: str) -> list[str]:
    return [spec.name for spec in PIPELINES[pipeline]]


def task_name(stage: str) -> str:
    return f"fotoskhema.{stage}"


def overall_progress(pipeline: str, stage: str, fraction: float) -> float:
    """Job progress 0-100 when ``stage`` is ``fraction`` done, weighting the stages."""
    specs = PIPELINES[pipeline]
    total = sum(s.weight for s in specs)
    done = 0.0
    for spec in specs:
        if spec.name == stage:
            return round(100.0 * (done + spec.weight * min(max(fraction, 0.0), 1.0)) / total, 2)
        done += spec.weight
    raise ValueError(f"stage {stage!r} is not part of the {pipeline!r} pipeline")


def stage_module(stage: str) -> ModuleType:
    return importlib.import_module(f"workers.stages.{stage}")


def stage_function(stage: str) -> Callable[..., dict[str, Any]]:
    """What runs ``stage`` whole in this process: its module's ``run``, or for a stage in parts its plan, its
    parts on this process's threads and its finish (:func:`run_parted`)."""
    module = stage_module(stage)
    if hasattr(module, "plan"):
        return lambda ws, cfg, progress=noop_progress: run_parted(module, stage, ws, cfg, progress)
    return module.run  # type: ignore[no-any-return]


def stage_spec(pipeline: str, stage: str) -> StageSpec:
    return next(spec for spec in PIPELINES[pipeline] if spec.name == stage)


def forget_parts_if_stale(ws: JobWorkspace, stage: str, rerun: bool = False) -> None:
    """Drop the records of ``stage``'s parts when it runs again after it had finished (asked to, or because files
    it wrote were lost since): they no longer say what is on disk. Parts of a stage that never finished (its
    worker died, its job was sent again) are kept: those are done."""
    if rerun or ws.load_stage_report(stage) is not None:
        ws.remove_parts(stage)


def stage_done(ws: JobWorkspace, stage: str) -> dict[str, Any] | None:
    """``stage``'s saved report when it ran and its files are all there; None when it must run."""
    done = ws.load_stage_report(stage)
    return done if done is not None and ws.stage_outputs_present(stage) else None


def run_stage(
    ws: JobWorkspace, pipeline: str, stage: str, progress: ProgressFn = noop_progress, rerun: bool = False
) -> dict[str, Any]:
    """Run one stage over ``ws`` unless its report says it already ran and its files are all there; save and
    return its report."""
    if not rerun and (done := stage_done(ws, stage)) is not None:
        return done
    forget_parts_if_stale(ws, stage, rerun)
    cfg = build_config(job_kind(pipeline), ws.load_config())
    started = time.perf_counter()
    report = stage_function(stage)(ws, cfg, progress=progress)
    report["wall_seconds"] = round(time.perf_counter() - started, 3)
    ws.save_stage_report(stage, report)
    return report


# A stage in parts: ``plan(ws, cfg) -> list[str]`` does what must come first (serially, idempotently) and names
# the parts; ``run_part(ws, cfg, key) -> dict`` does one, writing its files atomically, and returns its record
# (JSON, saved last: the mark that the part is done); ``finish(ws, cfg, records, progress=...) -> dict`` merges
# the records, read in the plan's order, into the stage's outputs and report. The parts' results depend on their
# keys only, so the stage's outputs are the same bytes whatever processes ran the parts and in whatever order.
# ``part_threads(cfg)``, if the module has it, is how many parts one process runs at once (default: a core each).
# ``PROGRESS_SHARES = (plan, parts)``, if the module has it, is what share of its progress planning and the parts
# take (the time-left estimate extrapolates a running stage's share done; finish has the rest).
PLAN_SHARE, PARTS_SHARE = 0.05, 0.85  # of a parted stage's progress, unless its module says otherwise


def progress_shares(module: ModuleType) -> tuple[float, float]:
    """(plan, parts) shares of a parted stage's progress; finish has the rest."""
    plan, parts = getattr(module, "PROGRESS_SHARES", (PLAN_SHARE, PARTS_SHARE))
    return float(plan), float(parts)


def plan_stage(module: ModuleType, stage: str, ws: JobWorkspace, cfg: Any) -> list[str]:
    """Plan ``stage`` and save the plan; return the keys of its parts not yet done (all, first time)."""
    started = time.time()
    keys = module.plan(ws, cfg)
    ws.save_plan(stage, keys, started)
    done = ws.parts_done(stage)
    return [k for k in keys if k not in done]


def run_parts(
    module: ModuleType, stage: str, ws: JobWorkspace, cfg: Any, keys: list[str], progress: ProgressFn
) -> None:
    """Run the parts ``keys`` of ``stage`` on this process's threads (or, inside :func:`parts_in_processes`, on its
    worker processes), saving each record as it is done; a part already done (by another worker, or before a
    restart) is skipped."""
    done = ws.parts_done(stage)
    todo = [key for key in keys if key not in done]
    if _PART_PROCESSES > 1 and len(todo) > 1:
        _run_in_processes(_PART_PROCESSES, module, stage, ws, cfg, keys, todo, progress)
        return
    threads = module.part_threads(cfg) if hasattr(module, "part_threads") else thread_count(cfg.threads)

    def one(key: str) -> None:
        if key not in done:
            run_one_part(module, stage, ws, cfg, key)

    ordered_map(one, keys, threads, progress, part_unit(module))


def run_one_part(module: ModuleType, stage: str, ws: JobWorkspace, cfg: Any, key: str) -> None:
    """Part ``key`` of ``stage``, its record saved with who did it and how long it took (for the report)."""
    started = time.perf_counter()
    record = module.run_part(ws, cfg, key)
    record["_done_by"] = f"{socket.gethostname()}:{os.getpid()}"
    record["_seconds"] = round(time.perf_counter() - started, 3)
    ws.save_part(stage, key, record)


# -- parts on worker processes (process_directory's ``processes``) ----------------------------------------------

_PART_PROCESSES = 1  # worker processes for a stage's parts (parts_in_processes); 1: threads


@contextmanager
def parts_in_processes(processes: int) -> Iterator[None]:
    """Within it, the parts of every parted stage run in this process go to ``processes`` spawned worker processes,
    a part each at a time with one thread (``threads`` 1), as Celery's workers would take them: a process's
    threads share one interpreter lock (a part's Python between its array calls), one page-fault lock and GDAL's
    block cache; 16 threads composed a strip only 2.4x faster than one on a 16-core host (not diagnosed further
    there). Each worker holds its share of the block caches (GDAL's, the JPEG blocks'), so that all of them hold
    what one process would. The workers are started for a stage's parts and stopped when they are done: what they
    held (their caches, freed arrays the allocator kept, a GPU context) is returned before the stage's finish,
    which runs here, and the next stage's parts. ``processes`` <= 1: threads."""
    global _PART_PROCESSES
    previous, _PART_PROCESSES = _PART_PROCESSES, max(1, processes)
    try:
        yield
    finally:
        _PART_PROCESSES = previous


@contextmanager
def _part_pool(processes: int) -> Iterator[ProcessPoolExecutor]:
    import multiprocessing

    pool = ProcessPoolExecutor(
        max_workers=processes,
        mp_context=multiprocessing.get_context("spawn"),  # no fork of a process with threads and GDAL handles
        initializer=_init_part_process,
        initargs=(processes,),
    )
    try:
        yield pool
    finally:
        pool.shutdown(wait=True, cancel_futures=True)


def _init_part_process(processes: int) -> None:
    """A part worker's share of the caches (at least 64 MiB each), and OpenCV on one thread: the parts are the
    unit of parallelism here."""
    from workers import GDAL_CACHE_MB

    share = max(64, int(os.environ.get("GDAL_CACHEMAX", GDAL_CACHE_MB)) // processes)
    os.environ["GDAL_CACHEMAX"] = str(share)
    from workers.tiff_jpeg import BLOCK_CACHE

    BLOCK_CACHE.max_bytes = max(64 * 2**20, BLOCK_CACHE.max_bytes // processes)
    import cv2

    cv2.setNumThreads(1)


def _part_in_process(module_name: str, stage: str, root: str, cfg: Any, key: str) -> None:
    run_one_part(importlib.import_module(module_name), stage, JobWorkspace(Path(root)), cfg, key)


def _run_in_processes(
    processes: int,
    module: ModuleType,
    stage: str,
    ws: JobWorkspace,
    cfg: Any,
    keys: list[str],
    todo: list[str],
    progress: ProgressFn,
) -> None:
    """The parts ``todo`` (of ``keys``) on up to ``processes`` worker processes of their own, progress reported here
    as they finish; the workers are gone when it returns."""
    # the frames' blocks this process decoded (its plan's reads) serve neither the workers nor the finish, which
    # reads what the parts wrote: 512 MiB returned while the workers hold theirs
    BLOCK_CACHE.clear()
    release_freed_memory()
    one_thread = cfg.model_copy(update={"threads": 1})
    root, unit = str(Path(ws.root).resolve()), part_unit(module)
    with _part_pool(min(processes, len(todo))) as pool:
        futures = [pool.submit(_part_in_process, module.__name__, stage, root, one_thread, key) for key in todo]
        finished = len(keys) - len(todo)
        try:
            for future in as_completed(futures):
                try:
                    future.result()  # a part's error is the stage's
                except BrokenProcessPool:
                    raise PipelineError(
                        f"a worker process died during {stage} (out of memory, or killed); the parts done are kept"
                    ) from None
                finished += 1
                progress(finished / len(keys), f"{unit} {finished}/{len(keys)}")
        finally:
            for future in futures:
                future.cancel()
            wait(futures)  # none left running on the job's files


def part_unit(module: ModuleType) -> str:
    """What one part of a stage is, in its progress ("frame 3/12"): the module's ``PART_UNIT``, else "part"."""
    return str(getattr(module, "PART_UNIT", "part"))


def finish_stage(module: ModuleType, stage: str, ws: JobWorkspace, cfg: Any, progress: ProgressFn) -> dict[str, Any]:
    """``stage``'s finish over every part's record, in the plan's order; what the parts freed and glibc kept for
    them (``parallel.keep_freed_memory``) is given back first, so the finish's arrays do not come on top of it
    (the Brighton strip: compose's finish peaked at 285 MiB, now 237, under its parts' 259-271)."""
    release_freed_memory()
    records = {key: ws.load_part(stage, key) for key in ws.load_plan(stage)}
    report: dict[str, Any] = module.finish(ws, cfg, records, progress=progress)
    return report


def run_parted(module: ModuleType, stage: str, ws: JobWorkspace, cfg: Any, progress: ProgressFn) -> dict[str, Any]:
    """A stage in parts, whole in this process: plan, the parts on threads, finish."""
    progress(0.0, "planning")
    plan, parts = progress_shares(module)
    started = time.perf_counter()
    todo = plan_stage(module, stage, ws, cfg)
    planned = time.perf_counter()
    run_parts(module, stage, ws, cfg, todo, lambda f, d: progress(plan + parts * f, d))
    parted = time.perf_counter()
    report = finish_stage(module, stage, ws, cfg, lambda f, d: progress(plan + parts + (1.0 - plan - parts) * f, d))
    report["parts"] = parts_summary(ws, stage)
    # the serial plan and finish against the parts, which more workers shorten
    marks = (started, planned, parted, time.perf_counter())
    report["phase_seconds"] = {k: round(marks[n + 1] - marks[n], 3) for n, k in enumerate(("plan", "parts", "finish"))}
    return report


def parts_summary(ws: JobWorkspace, stage: str) -> dict[str, Any]:
    """How many parts the stage had, and how many each worker process did in how many seconds (``host:pid``)."""
    by: dict[str, dict[str, float]] = {}
    keys = ws.load_plan(stage)
    for key in keys:
        record = ws.load_part(stage, key)
        entry = by.setdefault(str(record.get("_done_by", "?")), {"parts": 0, "seconds": 0.0})
        entry["parts"] += 1
        entry["seconds"] = round(entry["seconds"] + float(record.get("_seconds", 0.0)), 3)
    return {"count": len(keys), "by": by}


def _inspect(path: Path) -> dict[str, Any]:
    """A photo's entry for :func:`process_directory`, as an upload's check makes it (PipelineError naming it)."""
    from workers.image_meta import InvalidImageError, inspect_image

    try:
        return {"name": path.name, "path": str(path.resolve()), **inspect_image(path)}
    except InvalidImageError as exc:
        raise PipelineError(f"{path.name}: {exc}") from None


def process_directory(
    src_dir: Path,
    out_dir: Path,
    options: dict[str, Any] | None = None,
    progress: Callable[[str, float, str], None] | None = None,
    processes: int = 1,
) -> dict[str, Any]:
    """Run the whole mosaic pipeline in this process over the images in ``src_dir``.

    ``out_dir`` becomes the job workspace: ``mosaic.tif`` and ``report.json`` end up there. ``processes`` > 1:
    the photos' checks and the stages' parts run on that many worker processes (:func:`parts_in_processes`), not
    this one's threads.
    """
    from workers.gps_file import GPS_FILE_NAMES, parse_gps_file, with_side_file_gps

    paths = sorted(p for p in Path(src_dir).iterdir() if p.suffix.lower() in {".jpg", ".jpeg", ".png", ".tif", ".tiff"})
    # on the worker processes when there are some: a JPEG-in-TIFF strip frame's check is thousands of block decodes,
    # each with Python around it under one interpreter lock (40 frames, 2 cores: 9.9-10.5 s on threads, 8.1-8.4 s
    # on processes; the H200 machine's 16 threads took 20 s); else a thread per core (Pillow decodes without it)
    executor: AbstractContextManager[Executor] = (
        _part_pool(min(processes, len(paths)))
        if processes > 1 and len(paths) > 1
        else ThreadPoolExecutor(max_workers=os.cpu_count() or 1)
    )
    with executor as pool:
        frames = list(pool.map(_inspect, paths))
    side_file = next((Path(src_dir) / n for n in GPS_FILE_NAMES if (Path(src_dir) / n).exists()), None)
    if side_file is not None:  # geo.txt or gps.csv beside the photos: its positions over EXIF's, as jobs do
        try:
            fixes = {f.name: f for f in parse_gps_file(side_file.name, side_file.read_text(encoding="utf-8")).fixes}
        except (UnicodeDecodeError, ValueError) as exc:
            raise PipelineError(f"{side_file.name}: {exc}") from None
        frames = [with_side_file_gps(frame, side_file.name, fixes) for frame in frames]
    if len(frames) < 2:
        raise PipelineError(f"{src_dir} holds {len(frames)} usable image(s); a mosaic needs at least 2")
    ws = JobWorkspace(out_dir)
    ws.save_config(build_config(JobKind.mosaic, options).model_dump())
    ws.save_inputs(frames)
    pipeline = pipeline_key(JobKind.mosaic, options)
    with parts_in_processes(processes):
        for name in stage_names(pipeline):
            stage_progress = (lambda f, d, _n=name: progress(_n, f, d)) if progress else noop_progress
            run_stage(ws, pipeline, name, stage_progress)
    return ws.load_report()
