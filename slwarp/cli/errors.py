"""What the `slwarp` command reports as bad input (one line, exit status 2) and what it treats as a bug (its
traceback kept)."""
from __future__ import annotations

import os
import sys

__all__ = ["UserError"]


class UserError(Exception):
    """An error caused by the user's input: printed as one line, exit status 2."""


def _user_errors() -> tuple:
    """The exceptions that report bad input (printed as one line); every other exception is a bug."""
    from ..decode.frames import MissingFrames
    from ..devices import DeviceError
    from ..neural.config import ConfigError
    from ..neural.training import CheckpointError, TrainingDiverged
    from ..scans.scan import ScanError
    from ..scans.scanner import CalibrationError

    # OSError: a file that cannot be found, read or written (a missing folder, no permission, a full disk, an
    # output folder that is a file); CheckpointError: a truncated checkpoint, --resume of another run, a new
    # run over a checkpoint
    return (UserError, ScanError, CalibrationError, ConfigError, DeviceError, MissingFrames, OSError, TrainingDiverged,
            CheckpointError)


# Commands whose library code reports input that does not fit (a method the scan has no codes for, a
# triangulation it cannot do) as a plain ValueError: there it is a user error too.
_VALUE_ERRORS_ARE_USER_ERRORS = {"decode"}


def _interrupted():
    """TrainingInterrupted (a signal stopped training after its checkpoint): reported with its own exit status."""
    from ..neural.training import TrainingInterrupted

    return TrainingInterrupted


def _report(args, error: Exception) -> int:
    """A user error as one line on stderr (exit status 2); SLWARP_DEBUG=1 re-raises it with its traceback."""
    if os.environ.get("SLWARP_DEBUG"):
        raise error
    print(f"slwarp {args.command}: error: {error}", file=sys.stderr)
    return 2
