"""The CUDA driver and a GPU's context started in a thread through ctypes, before torch is imported.

    start_driver(0)   # first thing in a process that will compute on its cuda:0; returns at once

Why: a process's CUDA start has two parts, cuInit and the device's primary context (about 0.45 s on an H200 host,
torch's `torch.cuda.init()` and first allocation), and torch makes both on the main thread, holding the interpreter
lock, after its import (about 1.5 s). Several processes starting CUDA at once wait on each other inside the driver:
four on a 4 x H200 host took up to 1.7 s each against 0.45 alone (bench/results/cuda-start-cuda-h200x4.md). Called through ctypes, both
leave the interpreter lock free, so they run beside the imports; torch and Warp then find the driver initialised and
the context made (the runtime API and Warp both use the device's primary context), and count a start up. Used by a
batch's worker processes and torchrun's ranks (each sees one GPU), and for cuInit alone by a single scan's command.
`smallest_gpu_memory_gib()` reads the GPUs' memory through NVML the same way, for the command's batch default.
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


def smallest_gpu_memory_gib() -> float | None:
    """The total memory (GiB) of the smallest GPU the NVIDIA driver lists (NVML, through ctypes: no torch, no CUDA
    context), or None without the driver's NVML library or a GPU. Every GPU counts, not only those
    CUDA_VISIBLE_DEVICES shows (NVML numbers them its own way): a bound for all of them."""
    if not sys.platform.startswith("linux"):
        return None
    import ctypes

    try:
        nvml = ctypes.CDLL("libnvidia-ml.so.1")
        if nvml.nvmlInit_v2() != 0:
            return None
        count = ctypes.c_uint()
        if nvml.nvmlDeviceGetCount_v2(ctypes.byref(count)) != 0 or count.value == 0:
            return None
        sizes = []
        for index in range(count.value):
            handle, memory = ctypes.c_void_p(), (ctypes.c_ulonglong * 3)()  # nvmlMemory_t: total, free, used
            if nvml.nvmlDeviceGetHandleByIndex_v2(index, ctypes.byref(handle)) != 0 or \
                    nvml.nvmlDeviceGetMemoryInfo(handle, ctypes.byref(memory)) != 0:
                return None
            sizes.append(memory[0] / 2**30)
        return min(sizes)
    except (OSError, AttributeError):  # no driver library, or one without these calls
        return None
