"""The ``fotoskhema`` command: run the service's parts, or the pipeline on a folder without them."""

from __future__ import annotations

import argparse
import json
import os
import re
import signal
import sys
from pathlib import Path
from typing import Any


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="fotoskhema", description="Fotoskhema photogrammetry service.")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    up = sub.add_parser("up", help="everything on this machine: Redis, one Celery worker and the API + viewer")
    _add_http_args(up, "127.0.0.1", workers=max(1, min(4, _cores() // 2)))  # the other half: the worker
    up.add_argument("--queues", default="cpu,gpu", help="queues the embedded worker consumes")
    serve = sub.add_parser("serve", help="the REST API, tile server and viewer only")
    _add_http_args(serve, "127.0.0.1", workers=min(4, _cores()))
    worker = sub.add_parser("worker", help="a Celery worker running pipeline stages")
    worker.add_argument(
        "--queues", default="", help="comma-separated queues to consume (default: cpu; gpu,cpu with --gpu)"
    )
    worker.add_argument("--concurrency", type=int, default=1, help="parallel tasks in this worker")
    worker.add_argument(
        "--gpu", type=int, default=None, metavar="N",
        help="a GPU worker for device N only (CUDA_VISIBLE_DEVICES=N): one such process per GPU of the host",
    )  # fmt: skip
    from api.accounts_cli import add_users_parser  # noqa: PLC0415 - keep the import list of --help short

    add_users_parser(sub)
    process = sub.add_parser("process", help="run the mosaic pipeline on a folder of photos, no service needed")
    process.add_argument("directory", type=Path, help="folder of overlapping photos (JPEG, PNG, TIFF)")
    process.add_argument("-o", "--output", type=Path, required=True, help="output folder (mosaic.tif, report.json)")
    process.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="pipeline option, e.g. --set working_max_px=1600 (repeatable)",
    )
    process.add_argument(
        "--processes",
        type=int,
        default=1,
        help="run the stages' parts (frames, pairs, bands of the mosaic) on this many worker processes, a core each "
        "(default 1: this process's threads)",
    )
    return parser


def _add_http_args(parser: argparse.ArgumentParser, host: str, workers: int) -> None:
    parser.add_argument("--host", default=host, help="interface to listen on")
    parser.add_argument("--port", type=int, default=8000, help="TCP port")
    parser.add_argument(
        "--workers", type=int, default=workers, help=f"API processes (uvicorn workers; default {workers} here)"
    )


def _cores() -> int:
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    from api.accounts_cli import run_users  # noqa: PLC0415

    handler = {"up": _up, "serve": _serve, "worker": _worker, "process": _process, "users": run_users}[args.command]
    return int(handler(args) or 0)


def _serve(args: argparse.Namespace) -> int:
    import uvicorn  # noqa: PLC0415 - keep `fotoskhema --help` fast

    from core.db import Database  # noqa: PLC0415
    from core.settings import get_settings  # noqa: PLC0415

    settings = get_settings()
    settings.data_dir.mkdir(parents=True, exist_ok=True)
    db = Database(settings.resolved_database_url())  # the schema, made once before the API processes start
    from core.accounts import has_users  # noqa: PLC0415

    if not has_users(db):
        print("fotoskhema: no users yet: `fotoskhema users create NAME --admin` prints a token", flush=True)
    uvicorn.run(
        "api.main:create_app", factory=True, host=args.host, port=args.port, workers=args.workers, log_level="info"
    )
    return 0


def _worker(args: argparse.Namespace) -> int:
    queues = args.queues or ("gpu,cpu" if args.gpu is not None else "cpu")
    name: list[str] = []
    if args.gpu is not None:
        # Set before CuPy is imported (the worker imports it with the stages): this process sees device N as its
        # only one. The gpu queue brings it the GPU stages' parts; it takes cpu work too when it has nothing else.
        os.environ["CUDA_VISIBLE_DEVICES"] = str(args.gpu)
        name = ["-n", f"gpu{args.gpu}@%h"]  # several workers on one host need distinct names
    from workers.celery_app import app  # noqa: PLC0415

    argv = ["worker", "--loglevel", "INFO", "-Q", queues, "--concurrency", str(args.concurrency), *name]
    # workers need not know each other: the database and Redis coordinate them
    app.worker_main([*argv, "--without-gossip", "--without-mingle"])
    return 0


def _up(args: argparse.Namespace) -> int:
    from api.embedded_stack import Supervised, start_redis, start_worker  # noqa: PLC0415
    from core.settings import get_settings  # noqa: PLC0415

    # uvicorn re-raises SIGTERM once it has shut down; turn it into SystemExit so the children stop too.
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(0))
    settings = get_settings()
    settings.data_dir.mkdir(parents=True, exist_ok=True)
    redis_shown = re.sub(r"://[^@/]*@", "://***@", settings.redis_url)  # never print its password
    print(f"fotoskhema: data in {settings.data_dir.resolve()}, Redis at {redis_shown}", flush=True)
    from api.accounts_cli import announce_admin_token  # noqa: PLC0415

    token = announce_admin_token(settings)  # a fresh data dir gets an admin token, printed once
    worker_env = {"FOTOSKHEMA_DATA_DIR": str(settings.data_dir.resolve())}
    # Redis first: the worker waits for it, and each is started again when it dies.
    redis = Supervised("redis", lambda: start_redis(settings.redis_url, settings.data_dir / "redis"))
    worker = Supervised("worker", lambda: start_worker(args.queues, 1, worker_env))
    redis.start()
    worker.start()
    try:
        sign_in = f"#token={token}" if token else ""  # the viewer stores it and takes it out of the address
        print(f"fotoskhema: viewer on http://{args.host}:{args.port}/{sign_in}", flush=True)
        return _serve(args)
    finally:
        worker.stop()
        redis.stop()


def _process(args: argparse.Namespace) -> int:
    from workers.pipeline import PipelineError, process_directory  # noqa: PLC0415
    from workers.workspace import JobWorkspace  # noqa: PLC0415

    options = dict(_parse_option(item) for item in args.set)

    def report_progress(stage: str, fraction: float, detail: str) -> None:
        print(f"\r{stage:16s} {100 * fraction:5.1f}%  {detail:40s}", end="", file=sys.stderr, flush=True)

    try:
        report = process_directory(
            args.directory, args.output, options, progress=report_progress, processes=args.processes
        )
    except (PipelineError, ValueError) as exc:
        print(f"\nfotoskhema: error: {exc}", file=sys.stderr)
        return 1
    print(file=sys.stderr)
    summary = {k: report[k] for k in ("tie_point_rms_px", "georeferenced", "crs", "gsd_m", "stage_seconds")}
    summary.update(
        mosaic=str(JobWorkspace(args.output).mosaic_path()),
        frames_used=len(report["frames_used"]),
        frames_rejected=report["frames_rejected"],
    )
    print(json.dumps(summary, indent=2))
    return 0


def _parse_option(item: str) -> tuple[str, Any]:
    key, sep, value = item.partition("=")
    if not sep or not key:
        raise SystemExit(f"fotoskhema: --set expects KEY=VALUE, got {item!r}")
    try:
        return key.strip(), json.loads(value)
    except json.JSONDecodeError:
        return key.strip(), value


if __name__ == "__main__":
    os.environ.setdefault("PYTHONUNBUFFERED", "1")
    sys.exit(main())
