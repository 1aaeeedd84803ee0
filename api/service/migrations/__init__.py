"""Alembic migrations of the Glint database (``script_location = api:migrations``)."""
