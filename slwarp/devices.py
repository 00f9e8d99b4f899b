"""Devices in one place: the torch device a run uses and the Warp device its kernels launch on.

    torch_device("auto")      -> cuda (the current CUDA device) when one is present, else cpu
    torch_device("cuda:1")    -> torch.device("cuda:1"), or DeviceError when CUDA is absent
    warp_device(tensor.device) -> "cuda:1" / "cpu": the Warp name of a torch device ("auto" and None too)
"""
from __future__ import annotations

import threading

import torch

from . import timeline
from .neural.config import DEVICE_PATTERN  # the device names a user may give: the config checks them too

__all__ = ["DeviceError", "torch_device", "with_index", "warp_device", "start_runtimes", "runtimes_started",
           "DEVICE_PATTERN"]


class DeviceError(ValueError):
    """A device that is malformed or not present on this machine."""


# names users try that slwarp cannot run on, and what to say about them
_DEVICE_HINTS = {"gpu": "for an NVIDIA GPU give cuda or cuda:N", "mps": "Apple GPUs are not supported: the Warp kernels "
                 "run on the CPU and CUDA devices", "xpu": "Intel GPUs are not supported: the Warp kernels run on the CPU "
                 "and CUDA devices"}


def torch_device(spec: str | torch.device | None = "auto") -> torch.device:
    """The torch device for 'auto' (CUDA when present, else the CPU), 'cpu', 'cuda' or 'cuda:N'."""
    if isinstance(spec, torch.device):
        dev = spec
    elif spec is None or spec == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    elif isinstance(spec, str) and DEVICE_PATTERN.fullmatch(spec):
        dev = torch.device(spec)
    else:
        hint = _DEVICE_HINTS.get(str(spec).split(":")[0].strip().lower())
        raise DeviceError(f"device must be 'auto', 'cpu', 'cuda' or 'cuda:N', got {spec!r}" + (f" ({hint})" if hint else ""))
    if dev.type == "cuda":
        if not torch.cuda.is_available():
            raise DeviceError(f"device {spec}: CUDA was requested but no CUDA device is available")
        if dev.index is not None and dev.index >= torch.cuda.device_count():
            raise DeviceError(f"device {spec}: this machine has {torch.cuda.device_count()} CUDA device(s)")
    elif dev.type != "cpu":
        raise DeviceError(f"slwarp runs on the CPU or CUDA devices, got {dev}")
    return dev


def with_index(device: torch.device) -> torch.device:
    """`device` with its index: a CUDA device without one becomes torch's current CUDA device (made current now).
    torch's stream and graph calls look the current device up when given none, about 50 us each, 4 of them in every
    training step of a captured graph (cProfile of `slwarp reconstruct --preset fast`, one H200)."""
    if device.type == "cuda" and device.index is None:
        return torch.device("cuda", torch.cuda.current_device())
    return device


def warp_device(device: str | torch.device | None = "auto") -> str:
    """The Warp device name ('cpu', 'cuda:0', ...) of a torch device or device string; 'auto' and None
    pick as `torch_device` does. A CUDA device without an index is torch's current CUDA device."""
    if device is None or isinstance(device, str):
        device = torch_device(device or "auto")  # checks the name (a DeviceError naming it) and its presence
    dev = torch.device(device)
    if dev.type == "cuda":
        return f"cuda:{dev.index if dev.index is not None else torch.cuda.current_device()}"
    if dev.type != "cpu":
        raise DeviceError(f"Warp kernels run on CPU or CUDA devices, got {dev}")
    return "cpu"


def start_runtimes(device: torch.device) -> threading.Thread:
    """Start the runtimes a run on `device` needs, in a daemon thread: Warp (its library, the CUDA driver, the
    device list) and, on a GPU, torch's CUDA context and cuBLAS there. The command line starts them before it waits
    for the scan; the trainer's first CUDA call waits for a context being made (torch's lazy-init lock,
    slwarp.kernels.runtime's lock) instead of making another."""
    def run():
        try:
            from slwarp.kernels import runtime

            runtime.init()
            timeline.mark("warp started")
            if device.type == "cuda":
                torch.cuda.init()
                torch.empty(1, device=device)  # the context and the caching allocator's first block
                # cuBLAS's and cuBLASLt's handles (pooled: the trainer's thread takes them over) and first kernels,
                # which the first training step made: training 2.21 -> 2.09 s of a fresh `fast` command (one H100, 6
                # runs each, interleaved; bench/results/command-wall-cuda-h100-fast-blas-*.md)
                a = torch.ones(64, 64, device=device)
                (torch.nn.functional.linear(a, a) @ a).sum().item()
            timeline.mark("runtimes started")
        except Exception:  # noqa: BLE001 - the run's own first use reports it, where it happens
            pass

    thread = threading.Thread(target=run, name="slwarp-runtimes", daemon=True)
    thread.start()
    _STARTING.append(thread)
    return thread


_STARTING: list[threading.Thread] = []  # start_runtimes' threads


def runtimes_started(timeout: float = 30.0) -> None:
    """Wait (at most `timeout` s) for start_runtimes' threads. The command calls this before its process ends: on a
    machine without CUDA, Warp's start holds back stderr (kernels.runtime), and a line written meanwhile, e.g. an
    error about the scan, is only written out when the start is over."""
    while _STARTING:
        _STARTING.pop().join(timeout)
