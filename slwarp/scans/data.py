"""Where real captures live: the folder named by $SLWARP_DATA, each capture a sub-folder of it (e.g.
procam_chessboard/); without the variable, ../shared/data beside the repository (its development layout).
docs/real-captures.md says where to get the captures. Tests and benchmarks find them through `real_capture_dir`.
"""
from __future__ import annotations

import os
from pathlib import Path

__all__ = ["DATA_ENV", "DEFAULT_DATA", "CaptureNotFound", "data_dir", "real_capture_dir"]

DATA_ENV = "SLWARP_DATA"
# the development layout: shared/data beside the checkout (the package is slwarp/ in the repository's root)
DEFAULT_DATA = Path(__file__).resolve().parents[2].parent / "shared" / "data"


class CaptureNotFound(FileNotFoundError):
    """A real capture that is not in the data folder; the message says where it looked and how to point elsewhere."""


def data_dir() -> Path:
    """The folder holding the real captures: $SLWARP_DATA, else DEFAULT_DATA."""
    given = os.environ.get(DATA_ENV)
    return Path(given).expanduser() if given else DEFAULT_DATA


def real_capture_dir(name: str) -> Path:
    """The folder of the real capture `name` (e.g. "procam_chessboard") in data_dir(); CaptureNotFound when it is
    not there."""
    folder = data_dir() / name
    if not folder.is_dir():
        where = (f"{DATA_ENV}={os.environ[DATA_ENV]}" if os.environ.get(DATA_ENV)
                 else f"the default; set {DATA_ENV}=FOLDER, the folder that holds {name}/")
        raise CaptureNotFound(f"real capture {name!r} not found at {folder} ({where}; docs/real-captures.md says "
                              "where to get it)")
    return folder
