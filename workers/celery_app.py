"""The Celery application. Importing it loads no stage code, so the API can use it to enqueue."""

from __future__ import annotations

from celery import Celery

from core.settings import get_settings


def make_celery(broker_url: str) -> Celery:
    """A Celery app on ``broker_url``; tasks are registered by ``workers.tasks`` in the worker only."""
    app = Celery("fotoskhema", broker=broker_url, backend=broker_url, include=["workers.tasks"])
    app.conf.update(
        task_acks_late=True,  # a task lost with its worker is redelivered; stages are idempotent
        task_reject_on_worker_lost=True,
        worker_prefetch_multiplier=1,  # stages are long: never hold a second one hostage
        task_serializer="json",
        result_serializer="json",
        accept_content=["json"],
        result_expires=24 * 3600,
        broker_connection_retry_on_startup=True,
        task_default_queue="cpu",
    )
    return app


app = make_celery(get_settings().redis_url)
