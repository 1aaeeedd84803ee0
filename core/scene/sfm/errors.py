"""Why structure from motion gave no scene, in terms a user can act on."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from core.errors import GlintError


class SfmError(GlintError):
    """SfM ran but could not recover a usable scene (too few images, no overlap,
    too few registered). ``unregistered`` names the images left out; ``report`` is
    the registration report (as written to ``sfm_report.json``) when mapping ran."""

    def __init__(
        self,
        message: str,
        *,
        unregistered: Sequence[str] = (),
        report: dict[str, Any] | None = None,
    ) -> None:
        super().__init__(message)
        self.reason = message
        self.unregistered = list(unregistered)
        self.report = report


class SfmCancelledError(GlintError):
    """``should_stop`` asked SfM to stop; nothing was written to the output folder."""
