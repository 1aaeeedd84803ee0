"""Building the command line imports no torch: ``glint serve``, ``glint worker``,
``glint keys`` and ``glint --help`` start without paying for it (1.7 s and ~1,400
modules a process); the subcommands that train or render import it when they run."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_building_the_parser_does_not_import_torch() -> None:
    code = (
        "import sys\n"
        "from core.cli import build_parser\n"
        "p = build_parser()\n"
        "p.parse_args(['eval', 'runs/x'])\n"
        "heavy = sorted(m for m in ('torch', 'numpy', 'numba', 'trimesh') if m in sys.modules)\n"
        "assert not heavy, heavy\n"
    )
    res = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True)
    assert res.returncode == 0, res.stderr[-2000:]


def test_the_chamfer_default_is_the_one_evaluation_uses() -> None:
    from core.cli import build_parser
    from core.evaluation.geometry import DEFAULT_CHAMFER_POINTS

    args = build_parser().parse_args(["eval", "runs/x"])
    assert args.points == DEFAULT_CHAMFER_POINTS == 1_000_000
