"""Glint's REST service: scenes, uploads, validation, jobs, artifacts and API keys.

``api`` depends on ``core`` (scene loaders for validation, the trainer for jobs);
``core`` never imports ``api``. The app factory is :func:`api.main.create_app`.
"""
