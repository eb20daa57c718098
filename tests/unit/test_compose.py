"""docker-compose.yml and the Dockerfiles, checked against the code (no docker engine needed).

Compose cannot run here, so these tests check on paper what would break a `docker compose up`: a
missing Dockerfile or COPY source, a command naming a subcommand the CLI lacks, an environment
variable the settings do not read, a database driver the image does not install, a queue no
worker consumes.
"""

from __future__ import annotations

import argparse
import importlib
import json
import re
import shlex
import tomllib
from importlib.metadata import packages_distributions
from pathlib import Path
from typing import Any

import pytest
import yaml
from sqlalchemy.engine import make_url

ROOT = Path(__file__).resolve().parents[2]
COMPOSE = ROOT / "docker-compose.yml"
APP_SERVICES = ("api", "worker-gpu", "worker-cpu")  # run our image, share the data volume


def load_compose() -> dict[str, Any]:
    return dict(yaml.safe_load(COMPOSE.read_text()))


# --- helpers ---


def services() -> dict[str, dict[str, Any]]:
    return load_compose()["services"]


def argv_of(command: str | list[str]) -> list[str]:
    return shlex.split(command) if isinstance(command, str) else list(command)


def subcommands(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            return dict(action.choices)
    return {}


def check_entry_point(argv: list[str], where: str) -> None:
    """`fotoskhema X ...` must parse with the CLI's parser; `celery -A mod ...` must import mod."""
    if argv[0] == "fotoskhema":
        from api.cli import build_parser

        parser = build_parser()
        assert argv[1] in subcommands(parser), f"{where}: no subcommand {argv[1]!r} in api.cli"
        try:
            parser.parse_args(argv[1:])
        except SystemExit:
            pytest.fail(f"{where}: api.cli rejects the arguments {argv[1:]}")
    elif argv[0] == "celery":
        module = argv[argv.index("-A") + 1]
        assert hasattr(importlib.import_module(module), "app"), f"{where}: {module} has no Celery app"


def dockerfile_cmd(path: Path) -> list[str]:
    cmds = [ln[3:].strip() for ln in path.read_text().splitlines() if ln.startswith("CMD ")]
    assert cmds, f"{path.name} has no CMD"
    return json.loads(cmds[-1])  # exec form only: a shell form would not receive signals


def build_dockerfile(build: str | dict[str, Any]) -> Path:
    if isinstance(build, str):
        return ROOT / build / "Dockerfile"
    return ROOT / build.get("context", ".") / build.get("dockerfile", "Dockerfile")


# --- the tests ---


def test_every_built_image_has_a_dockerfile_whose_copy_sources_exist() -> None:
    built = {name: svc["build"] for name, svc in services().items() if "build" in svc}
    assert set(built) == set(APP_SERVICES)
    ignored = {ln.strip() for ln in (ROOT / ".dockerignore").read_text().splitlines()}
    for name, build in built.items():
        dockerfile = build_dockerfile(build)
        assert dockerfile.is_file(), f"{name}: {dockerfile} is missing"
        for line in dockerfile.read_text().splitlines():
            if line.startswith("COPY ") and "--from=" not in line:
                for src in (w for w in line.split()[1:-1] if not w.startswith("--")):
                    assert (dockerfile.parent / src).exists(), f"{dockerfile.name} copies missing {src}"
                    assert src not in ignored, f"{dockerfile.name} copies {src}, which .dockerignore drops"


def test_commands_and_healthchecks_name_real_entry_points() -> None:
    for name, svc in services().items():
        if "command" in svc:
            check_entry_point(argv_of(svc["command"]), f"{name}.command")
        test = svc["healthcheck"]["test"]
        if test[0] == "CMD-SHELL" and test[1].startswith("celery "):
            check_entry_point(shlex.split(test[1]), f"{name}.healthcheck")


@pytest.mark.parametrize("name", ["Dockerfile", "Dockerfile.gpu"])
def test_dockerfile_cmd_names_a_real_subcommand(name: str) -> None:
    argv = dockerfile_cmd(ROOT / name)
    assert argv[0] == "fotoskhema"
    check_entry_point(argv, f"{name} CMD")


def test_every_service_has_a_healthcheck() -> None:
    for name, svc in services().items():
        test = svc.get("healthcheck", {}).get("test")
        assert test and test[0] in ("CMD", "CMD-SHELL"), f"{name} has no healthcheck"


def test_api_and_workers_share_the_data_volume() -> None:
    compose = load_compose()
    assert "data" in compose["volumes"]
    for name in APP_SERVICES:
        svc = compose["services"][name]
        assert "data:/data" in svc.get("volumes", []), f"{name} does not mount the data volume at /data"
        assert svc["environment"]["FOTOSKHEMA_DATA_DIR"] == "/data"


def test_the_import_directory_is_mounted_read_only_and_allowed(monkeypatch: pytest.MonkeyPatch) -> None:
    from core.settings import Settings

    api = services()["api"]
    monkeypatch.setenv("FOTOSKHEMA_IMPORT_DIRS", api["environment"]["FOTOSKHEMA_IMPORT_DIRS"])
    allowed = Settings().import_dirs
    mounts = {v.split(":")[-2]: v.split(":")[-1] for v in api["volumes"] if v.count(":") >= 2}
    assert allowed and all(mounts.get(str(d)) == "ro" for d in allowed), (allowed, api["volumes"])


def test_gpu_worker_reserves_an_nvidia_device() -> None:
    devices = services()["worker-gpu"]["deploy"]["resources"]["reservations"]["devices"]
    assert any(d["driver"] == "nvidia" and d["count"] >= 1 and "gpu" in d["capabilities"] for d in devices)
    assert "gpu" in dockerfile_cmd(ROOT / "Dockerfile.gpu")


def test_settings_read_the_environment_compose_sets(monkeypatch: pytest.MonkeyPatch) -> None:
    from core.settings import Settings

    env = services()["api"]["environment"]
    for key, value in env.items():
        monkeypatch.setenv(key, str(value))
    settings = Settings()
    assert settings.data_dir == Path(env["FOTOSKHEMA_DATA_DIR"])
    assert settings.resolved_database_url() == env["DATABASE_URL"]
    assert settings.redis_url == env["REDIS_URL"]
    assert settings.celery_queue == env["FOTOSKHEMA_CELERY_QUEUE"]


def worker_queues(svc: dict[str, Any]) -> set[str]:
    argv = argv_of(svc["command"])
    return set(argv[argv.index("--queues") + 1].split(","))


def test_the_api_queue_is_consumed_with_and_without_a_gpu() -> None:
    from core.settings import Settings

    svcs = services()
    queue = svcs["api"]["environment"]["FOTOSKHEMA_CELERY_QUEUE"]
    assert queue in worker_queues(svcs["worker-gpu"])
    assert queue in worker_queues(svcs["worker-cpu"]), "without a GPU, no worker would run the jobs"
    assert "deploy" not in svcs["worker-cpu"]
    # the GPU stages' parts go to the gpu queue when a worker there is alive: only the GPU worker consumes it
    gpu_queue = Settings().gpu_queue
    assert gpu_queue in worker_queues(svcs["worker-gpu"]) and gpu_queue not in worker_queues(svcs["worker-cpu"])
    assert "--gpu" in argv_of(svcs["worker-gpu"]["command"])


def test_urls_point_at_compose_services_and_agree_everywhere() -> None:
    svcs = services()
    for key in ("DATABASE_URL", "REDIS_URL"):
        urls = {svcs[name]["environment"][key] for name in APP_SERVICES}
        assert len(urls) == 1, f"{key} differs between services: {urls}"
        assert make_url(urls.pop()).host in svcs
    url = make_url(svcs["api"]["environment"]["DATABASE_URL"])
    pg = svcs["postgres"]["environment"]
    assert (url.username, url.password, url.database) == (
        pg["POSTGRES_USER"],
        pg["POSTGRES_PASSWORD"],
        pg["POSTGRES_DB"],
    )


def test_database_driver_comes_from_the_postgres_extra() -> None:
    url = make_url(services()["api"]["environment"]["DATABASE_URL"])
    driver_module = url.get_dialect().import_dbapi().__name__.split(".")[0]  # e.g. psycopg2
    providers = {d.lower() for d in packages_distributions().get(driver_module, [])}
    extra = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["optional-dependencies"]
    extra_names = {re.split(r"[<>=!~\[; ]", req, maxsplit=1)[0].lower() for req in extra["postgres"]}
    assert providers & extra_names, f"{url.drivername}: {driver_module} is not installed by [postgres]"
    for dockerfile in ("Dockerfile", "Dockerfile.gpu"):
        assert re.search(r"pip install .*\.\[[^\]]*postgres", (ROOT / dockerfile).read_text())


def test_image_points_the_settings_at_the_copied_viewer() -> None:
    from core.settings import Settings

    # A regular install puts api/ in site-packages, where the default web_dir (next to it) is empty.
    assert "web_dir" in Settings.model_fields
    text = (ROOT / "Dockerfile").read_text()
    assert "WORKDIR /app" in text and "COPY web web" in text and "FOTOSKHEMA_WEB_DIR=/app/web" in text
