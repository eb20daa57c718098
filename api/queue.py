"""How the API hands a job to the workers: a Celery chain of the job kind's stages, sent by task
name, so the API never imports the stage code (or OpenCV).

Every task of a chain carries the chain's token (``workers.liveness``); the job record names the newest, and
a task of an older chain stops, so a job sent again never runs two chains at once.
"""

from __future__ import annotations

import json
from typing import Protocol, runtime_checkable

import redis
from celery import chain

from workers.celery_app import make_celery
from workers.liveness import live_workers, new_token, redis_client
from workers.pipeline import stage_names, task_name

PROBE_TIMEOUT = 0.3  # s, each Redis call of the health check; it answers within a second when Redis is away
PRIORITY_SUFFIXES = ("", "\x06\x163", "\x06\x166", "\x06\x169")  # kombu's Redis list of each priority step


class JobQueue(Protocol):
    def enqueue(self, job_id: int, pipeline: str, after: str = "") -> str:
        """Send the stages of ``pipeline`` (see workers.pipeline.PIPELINES); return an id for the chain, newer
        than ``after`` (the job's previous one) whatever this host's clock says."""
        ...


@runtime_checkable
class MonitoredQueue(Protocol):
    def liveness(self, worker_max_age: float) -> dict[str, str]:
        """``broker`` and ``worker``: ``ok`` or ``down`` (no worker beacon in ``worker_max_age`` s)."""
        ...


class CeleryQueue:
    """Sends a job as ``chain(fotoskhema.<stage>(job_id, token=...), ...)`` on one queue."""

    def __init__(self, redis_url: str, queue: str) -> None:
        self.app = make_celery(redis_url)
        self.queue = queue
        self._redis = redis_client(redis_url, PROBE_TIMEOUT)

    def enqueue(self, job_id: int, pipeline: str, after: str = "") -> str:
        token = new_token(after)
        self.send(job_id, pipeline, token)
        return token

    def send(self, job_id: int, pipeline: str, token: str, from_stage: str = "") -> None:
        """Send the stages of ``pipeline`` from ``from_stage`` (default: the first) as chain ``token``."""
        names = stage_names(pipeline)
        names = names[names.index(from_stage) :] if from_stage in names else names
        signatures = [
            self.app.signature(
                task_name(stage),
                args=(job_id,),
                kwargs={"token": token},
                immutable=True,
                queue=self.queue,
                task_id=f"{token}.{stage}",  # pending_tokens finds the chain by it
            )
            for stage in names
        ]
        chain(*signatures).apply_async()

    def redis(self) -> redis.Redis:
        return self._redis

    def pending_tokens(self) -> set[str]:
        """Tokens of the chains with a message waiting in this queue's Redis lists (not those a worker holds)."""
        pipe = self._redis.pipeline(transaction=False)
        for suffix in PRIORITY_SUFFIXES:
            pipe.lrange(self.queue + suffix, 0, -1)
        tokens = set()
        for messages in pipe.execute():
            for raw in messages:
                try:
                    task_id = str(json.loads(raw)["headers"]["id"])
                except (ValueError, KeyError, TypeError):
                    continue
                tokens.add(task_id.partition(".")[0])
        return tokens

    def liveness(self, worker_max_age: float) -> dict[str, str]:
        try:
            self._redis.ping()
        except redis.RedisError:
            return {"broker": "down", "worker": "unknown"}
        try:
            workers = live_workers(self._redis, self.queue, worker_max_age)
        except redis.RedisError:
            return {"broker": "down", "worker": "unknown"}
        return {"broker": "ok", "worker": "ok" if workers else "down"}
