"""Warp's missing-driver warning: held back on CPU-only machines (SLWARP_VERBOSE=1 shows it), other output kept."""
from __future__ import annotations

import os
import subprocess
import sys

import pytest

from slwarp.kernels import runtime

# a tiny CPU launch in a fresh process (Warp prints the warning once, at its initialisation; Warp reads a kernel's
# source from its file, so the script is written to one)
LAUNCH = """
import numpy as np
import warp as wp
from slwarp.kernels import runtime

@wp.kernel
def twice(a: wp.array(dtype=float)):
    i = wp.tid()
    a[i] = 2.0 * a[i]

wp_ = runtime.init()
a = wp_.array(np.arange(4, dtype=np.float32), device="cpu")
wp_.launch(twice, dim=4, inputs=[a], device="cpu")
print(a.numpy().tolist())
"""


def test_cpu_launch_prints_no_cuda_warning(tmp_path):
    env = dict(os.environ)
    env.pop("SLWARP_VERBOSE", None)
    env["SLWARP_KERNEL_CACHE"] = str(tmp_path / "kernels")
    script = tmp_path / "launch.py"
    script.write_text(LAUNCH)
    run = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, env=env, timeout=300)
    assert run.returncode == 0, run.stderr
    assert run.stdout.strip() == "[0.0, 2.0, 4.0, 6.0]"
    assert "CUDA warning" not in run.stdout + run.stderr
    if runtime._cuda_driver_present():
        return  # the rest is about machines without the driver
    env["SLWARP_VERBOSE"] = "1"
    run = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, env=env, timeout=300)
    assert run.returncode == 0 and runtime.DRIVER_WARNING in run.stderr  # still there for those who ask


def test_held_back_output_keeps_every_other_line(capfd):
    with runtime._without_driver_warning():
        os.write(2, (runtime.DRIVER_WARNING + ". GPU execution will not be available.\n").encode())
        os.write(2, b"Warp CUDA error: something else\n")
    err = capfd.readouterr().err
    assert err == "Warp CUDA error: something else\n"


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="the driver's library name is Linux's")
def test_driver_check_matches_the_library(monkeypatch):
    import ctypes

    def no_library(name):
        raise OSError(f"{name}: cannot open shared object file")

    monkeypatch.setattr(ctypes, "CDLL", no_library)
    assert runtime._cuda_driver_present() is False
    monkeypatch.setattr(ctypes, "CDLL", lambda name: object())
    assert runtime._cuda_driver_present() is True
