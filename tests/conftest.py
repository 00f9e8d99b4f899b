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


@pytest.fixture(scope="session")
def tiny_rods_field():
    """(scan, config, trainer): a 60-iteration `tiny` field on the small-rig rods scene (CPU), trained once for
    the extraction tests; a test sets trainer.cfg to the extraction it wants."""
    from slwarp.neural.config import preset
    from slwarp.neural.train import Trainer
    from slwarp.sim.simulate import SimOptions, simulate_scene

    scan = simulate_scene("rods", "random6", rig="small", options=SimOptions(seed=0), device="cpu")
    cfg = preset("tiny", device="cpu", iters=60, init_iters=30)
    trainer = Trainer(scan, cfg, progress=False)
    trainer.train()
    return scan, cfg, trainer
