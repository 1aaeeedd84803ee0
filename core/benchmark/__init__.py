"""The ablation benchmark (``glint bench``): configurations, runner, tables."""
