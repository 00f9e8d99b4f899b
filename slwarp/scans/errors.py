"""ScanError: a scan that cannot be used, and calibration errors reported as one (naming the file)."""
from __future__ import annotations

from pathlib import Path
from typing import Callable, TypeVar

from .scanner import CalibrationError

__all__ = ["ScanError", "calibration_from"]

T = TypeVar("T")


class ScanError(ValueError):
    """A scan on disk (or in memory) that cannot be used: the message names the file and the problem."""


def calibration_from(where: Path, build: Callable[[], T]) -> T:
    """`build()` (a Camera or Projector from a file's values); its CalibrationError as a ScanError naming `where`."""
    try:
        return build()
    except CalibrationError as e:
        raise ScanError(f"{where}: {e}") from None
