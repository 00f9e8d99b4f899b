"""The CUDA driver and a GPU's context started in a thread through ctypes, before torch is imported.

    start_driver(0)   # first thing in a process that will compute on its cuda:0; returns at once

Why: a process's CUDA start has two parts, cuInit and the device's primary context (about 0.45 s on an H200 host,
torch's `torch.cuda.init()` and first allocation), and torch makes both on the main thread, holding the interpreter
lock, after its import (about 1.5 s). Several processes starting CUDA at once wait on each other inside the driver:
four on a 4 x H200 host took up to 1.7 s each against 0.45 alone (bench/results/cuda-start-cuda-h200x4.md). Called through ctypes, both
leave the interpreter lock free, so they run beside the imports; torch and Warp then find the driver initialised and
the context made (the runtime API and Warp both use the device's primary context), and count a start up. Used by a
batch's worker processes and torchrun's ranks (each sees one GPU), and for cuInit alone by a single scan's command.
"""
from __future__ import annotations

import sys
import threading

_RETAINED: list = []  # the primary contexts retained here: held until the process ends, as torch holds its own


def start_driver(ordinal: int | None = None) -> threading.Thread | None:
    """In a daemon thread: cuInit, NVML's start (torch counts the devices through it), and with `ordinal` the primary
    context of that device as the driver numbers it (CUDA_VISIBLE_DEVICES applies, so set it first). None, doing
    nothing, off Linux. Failures are silent: no driver or no such GPU is reported by the command's own first CUDA
    call, where it happens."""
    if not sys.platform.startswith("linux"):
        return None

    def run() -> None:
        import ctypes

        try:
            cuda = ctypes.CDLL("libcuda.so.1")
            if cuda.cuInit(0) != 0:  # no usable GPU: the command runs on the CPU or says why
                return
            try:
                ctypes.CDLL("libnvidia-ml.so.1").nvmlInit_v2()
            except (OSError, AttributeError):
                pass
            if ordinal is not None:
                device, context = ctypes.c_int(), ctypes.c_void_p()
                if cuda.cuDeviceGet(ctypes.byref(device), ordinal) == 0 and \
                        cuda.cuDevicePrimaryCtxRetain(ctypes.byref(context), device) == 0:
                    _RETAINED.append(context)
        except (OSError, AttributeError):  # no driver library
            pass

    thread = threading.Thread(target=run, name="slwarp-cuda-driver", daemon=True)
    thread.start()
    return thread

