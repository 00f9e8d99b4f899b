"""Warp runtime helpers: lazy init, the kernel cache location, and device/stream mapping from torch.

Warp is initialised on first use, never at import. The kernel cache goes to $SLWARP_KERNEL_CACHE, else
$WARP_CACHE_PATH, else Warp's default (per user). Kernels are pure functions of their source, so a warm
cache changes only compile time, never results or test order.
"""
from __future__ import annotations

import os
import threading

_lock = threading.Lock()
_ready = False


def init():
    """Initialise Warp once (quietly) and return the module."""
    global _ready
    import warp as wp

    if _ready:
        return wp
    with _lock:
        if not _ready:
            cache = os.environ.get("SLWARP_KERNEL_CACHE") or os.environ.get("WARP_CACHE_PATH")
            if cache:
                wp.config.kernel_cache_dir = cache
            if not os.environ.get("SLWARP_VERBOSE"):
                wp.config.log_level = 30  # warnings and errors only: no banner, no per-module load lines
            wp.init()
            _ready = True
    return wp


def warp_device(device) -> str:
    """A torch device (or string) -> Warp device name ('cpu', 'cuda:0', ...)."""
    import torch

    dev = torch.device(device)
    if dev.type == "cuda":
        return f"cuda:{dev.index if dev.index is not None else torch.cuda.current_device()}"
    if dev.type != "cpu":
        raise ValueError(f"Warp kernels run on CPU or CUDA devices, got {dev}")
    return "cpu"


class on_torch_stream:
    """Context: launch Warp work on torch's current stream of `device` (no-op on the CPU)."""

    def __init__(self, device):
        import torch

        self.dev = torch.device(device)
        self._ctx = None

    def __enter__(self):
        wp = init()
        if self.dev.type == "cuda":
            self._ctx = wp.ScopedStream(wp.stream_from_torch(self.dev))
            self._ctx.__enter__()
        return self

    def __exit__(self, *exc):
        if self._ctx is not None:
            self._ctx.__exit__(*exc)
        return False
