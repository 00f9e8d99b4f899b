"""Common test set-up: a fresh Warp kernel cache per test run (results never depend on a warm cache or on test
order), the devices to run on (CPU always, CUDA when present), and the real capture (found through $SLWARP_DATA:
slwarp.scans.data; the tests that need it are skipped without it)."""
from __future__ import annotations

import os
import tempfile

import pytest

if not os.environ.get("SLWARP_KERNEL_CACHE"):
    os.environ["SLWARP_KERNEL_CACHE"] = tempfile.mkdtemp(prefix="slwarp-kernels-")


def _devices():
    devs = ["cpu"]
    try:
        import torch

        torch.set_flush_denormal(True)  # CPU speed: see slwarp.neural.start.set_process_flags
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


@pytest.fixture
def capture_cuda_graph():
    """capture(step) -> (graph, step's outputs in the graph's memory): step() run once on a side stream (kernels
    built and launches recorded before the capture, as CUDA graphs require), then captured; replay the graph after
    copying new inputs into the tensors step reads."""
    import torch

    def capture(step):
        stream = torch.cuda.Stream()
        stream.wait_stream(torch.cuda.current_stream())
        with torch.cuda.stream(stream):
            step()
        torch.cuda.current_stream().wait_stream(stream)
        graph = torch.cuda.CUDAGraph()
        with torch.cuda.graph(graph):
            out = step()
        return graph, out

    return capture


@pytest.fixture(scope="session")
def chessboard_path():
    """The real capture procam_chessboard (docs/real-captures.md); the test is skipped, saying where it looked and
    which variable to set, when it is absent."""
    from slwarp.scans.data import CaptureNotFound, real_capture_dir

    try:
        return real_capture_dir("procam_chessboard")
    except CaptureNotFound as e:
        pytest.skip(str(e))


@pytest.fixture(scope="session")
def tiny_rods_field():
    """(scan, config, trainer): a 60-iteration `tiny` field on the small-rig rods scene (CPU), trained once for
    the extraction tests; a test sets trainer.cfg to the extraction it wants."""
    from slwarp.neural.config import preset
    from slwarp.neural.training import Trainer
    from slwarp.sim.simulate import SimOptions, simulate_scene

    scan = simulate_scene("rods", "random6", rig="small", options=SimOptions(seed=0), device="cpu")
    cfg = preset("tiny", device="cpu", iters=60, init_iters=30)
    trainer = Trainer(scan, cfg, progress=False)
    trainer.train()
    return scan, cfg, trainer
