"""Shared test set-up: a fresh Warp kernel cache per session (results never depend on a warm cache or
on test order), the devices to run on (CPU always, CUDA when present), and paths to shared data."""
from __future__ import annotations

import os
import tempfile
from pathlib import Path

import pytest

if not os.environ.get("SLWARP_KERNEL_CACHE"):
    os.environ["SLWARP_KERNEL_CACHE"] = tempfile.mkdtemp(prefix="slwarp-kernels-")

REPO = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("SLWARP_SHARED", REPO.parent / "shared"))
CHESSBOARD = SHARED / "data" / "procam_chessboard"


def _devices():
    devs = ["cpu"]
    try:
        import torch

        torch.set_flush_denormal(True)  # CPU speed: see slwarp.neural.train
        if torch.cuda.is_available():
            devs.append("cuda:0")
    except ImportError:  # pragma: no cover
        pass
    return devs


DEVICES = _devices()


@pytest.fixture(params=DEVICES)
def device(request):
    """Each test using it runs on the CPU and on every CUDA device present."""
    return request.param


@pytest.fixture(scope="session")
def chessboard_path():
    if not CHESSBOARD.is_dir():
        pytest.skip(f"real capture not found at {CHESSBOARD} (set SLWARP_SHARED)")
    return CHESSBOARD
