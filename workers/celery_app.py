"""The Celery application. Importing it loads no stage code, so the API can use it to enqueue."""

from __future__ import annotations

from celery import Celery

from core.settings import Settings, get_settings


def make_celery(broker_url: str, settings: Settings | None = None) -> Celery:
    """A Celery app on ``broker_url``; tasks are registered by ``workers.tasks`` in the worker only.

    Time limits and the visibility timeout come from ``settings`` (default: the process settings).
    """
    settings = settings or get_settings()
    # A stage may run for hours (a long strip on the CPU). The soft limit stops it with a message the job
    # records; the hard limit kills a stage that ignores it (stuck in C code) a little later.
    soft_limit = settings.stage_time_limit_seconds
    hard_limit = soft_limit + 600
    app = Celery("fotoskhema", broker=broker_url, backend=broker_url, include=["workers.tasks"])
    app.conf.update(
        task_acks_late=True,  # a task lost with its worker is redelivered; stages are idempotent
        task_reject_on_worker_lost=True,
        worker_prefetch_multiplier=1,  # stages are long: never hold a second one hostage
        task_soft_time_limit=soft_limit,
        task_time_limit=hard_limit,
        # Redis hands an unacknowledged message to another worker once the visibility timeout has passed. A
        # worker that died is noticed by the job's heartbeat instead (workers.liveness, api.reaper: within
        # Settings.stale_seconds), so this timeout is only a last resort and can be long; it must outlast
        # the longest stage, or a message would be handed out again while its stage still runs.
        broker_transport_options={"visibility_timeout": hard_limit + 3600},
        broker_connection_retry_on_startup=True,
        broker_connection_max_retries=None,  # a worker waits for Redis however long it is down
        worker_cancel_long_running_tasks_on_connection_loss=False,  # a stage goes on; the reaper sees to its end
        task_serializer="json",
        result_serializer="json",
        accept_content=["json"],
        result_expires=24 * 3600,
        task_default_queue="cpu",
    )
    return app


app = make_celery(get_settings().redis_url)
