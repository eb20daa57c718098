"""How the API hands a job to the workers: a Celery chain of the job kind's stages, sent by task
name, so the API never imports the stage code (or OpenCV)."""

from __future__ import annotations

from typing import Protocol

from celery import chain

from workers.celery_app import make_celery
from workers.pipeline import stage_names, task_name


class JobQueue(Protocol):
    def enqueue(self, job_id: int, pipeline: str) -> str:
        """Send the stages of ``pipeline`` (see workers.pipeline.PIPELINES); return an id for the chain."""
        ...


class CeleryQueue:
    """Sends a job as ``chain(fotoskhema.<stage>(job_id), ...)`` on one queue."""

    def __init__(self, redis_url: str, queue: str) -> None:
        self.app = make_celery(redis_url)
        self.queue = queue

    def enqueue(self, job_id: int, pipeline: str) -> str:
        signatures = [
            self.app.signature(task_name(stage), args=(job_id,), immutable=True, queue=self.queue)
            for stage in stage_names(pipeline)
        ]
        return str(chain(*signatures).apply_async().id)
