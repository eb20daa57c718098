"""Pipeline workers: Celery tasks over job workspaces, stage logic and pure algorithms."""
