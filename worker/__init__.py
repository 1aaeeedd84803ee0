"""Glint's Celery worker: runs training jobs from the Redis broker, one per GPU.

The task is a thin shell around :func:`api.service.runner.run_job`; the database, not
the broker, decides who runs what (see ``docs/worker.md``).
"""
