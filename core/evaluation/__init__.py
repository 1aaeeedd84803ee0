"""evaluation.

Constants the command line needs for its defaults live here, so that building the
parser (``glint serve``, ``glint worker``, ``glint --help``) does not import torch."""

DEFAULT_CHAMFER_POINTS = 1_000_000  # the data README's sampling floor is stated for 1M
