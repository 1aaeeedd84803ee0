"""One router module per resource: keys (and health), scenes, jobs, artifacts."""
