"""Command-line plumbing shared by the probes that measure one trained run against its
scene's ground truth (``bench.angle_error``, ``bench.single_view_target``)."""

from __future__ import annotations

import argparse
from pathlib import Path

import torch

from core.model.trained import TrainedModel
from core.scene.formats import load_scene
from core.scene.views import Scene


def run_scene_parser(doc: str | None) -> argparse.ArgumentParser:
    """A parser with the run folder and ``--scene``; the caller adds its own options."""
    ap = argparse.ArgumentParser(
        description=doc, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("run", type=Path)
    ap.add_argument("--scene", type=Path, required=True, help="scene folder with GT maps")
    return ap


def open_run_and_scene(args: argparse.Namespace) -> tuple[TrainedModel, Scene]:
    """The trained model (no autograd: probes only render) and its scene."""
    torch.set_grad_enabled(False)
    return TrainedModel.open(args.run), load_scene(args.scene)
