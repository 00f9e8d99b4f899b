"""What the torch-facing ops share: the backends, the working volume's bounds as kernels take them, and Warp
launches from torch tensors.

A launch costs a few microseconds of Python per kernel instead of a full wp.launch: arguments are array
descriptors made straight from torch tensors (`desc`), struct values filled from them by field name (`struct`),
and recorded launch commands whose parameters are rewritten (`slwarp.kernels.runtime.CachedLaunch`), on torch's
current stream without host synchronisation, so that a whole training step can be one CUDA graph.
"""
from __future__ import annotations

import threading

import numpy as np
import torch

from ...devices import warp_device
from ...scans.scanner import PackedProjector
from slwarp.kernels import runtime
from slwarp.kernels.geometry import camera_params, projector_params

BACKENDS = ("warp", "torch")

desc = runtime.array_desc
struct = runtime.struct_value

_PARAMS_CACHE: dict = {}
# each thread its own recorded launches: a launch rewrites its command's parameters before launching it, and a batch
# extracts one scan in a thread while the next trains in another, both through the same kernels
_LAUNCHERS = threading.local()
_STREAMS: dict = {}


def check_backend(backend: str):
    if backend not in BACKENDS:
        raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")


def bounds_list(bounds) -> list[float]:
    """[xmin, ymin, zmin, xmax, ymax, zmax] (mm) of the working volume; None = unbounded."""
    if bounds is None:
        return [-3.0e38, -3.0e38, -3.0e38, 3.0e38, 3.0e38, 3.0e38]
    if isinstance(bounds, (torch.Tensor, np.ndarray)):
        bounds = bounds.tolist()
    flat = [float(x) for row in bounds for x in (row if isinstance(row, (list, tuple)) else [row])]
    if len(flat) != 6:
        raise ValueError(f"bounds must be [[xmin, ymin, zmin], [xmax, ymax, zmax]], got {len(flat)} numbers")
    return flat


def projector_struct(projector):
    """The Warp struct of a packed projector (list or PackedProjector), made once per projector."""
    key = tuple(projector)
    prm = _PARAMS_CACHE.get(key)
    if prm is None:
        runtime.init()
        prm = _PARAMS_CACHE[key] = projector_params(PackedProjector(*key))
    return prm


def camera_struct(camera):
    """The Warp struct of a `slwarp.Camera`, made once per camera."""
    key = ("camera", camera.fx, camera.fy, camera.cx, camera.cy, *map(float, camera.dist))
    prm = _PARAMS_CACHE.get(key)
    if prm is None:
        runtime.init()
        prm = _PARAMS_CACHE[key] = camera_params(camera)
    return prm


def vec3(values):
    wp = runtime.init()
    return wp.vec3(*values)


def launch(kernel, dim, inputs, device: torch.device):
    """Launch on torch's current stream of `device` (asynchronous: no host synchronisation)."""
    launchers = getattr(_LAUNCHERS, "by_kernel", None)
    if launchers is None:
        launchers = _LAUNCHERS.by_kernel = {}
    launcher = launchers.get(kernel)
    if launcher is None:
        # 64-thread blocks: one thread per ray leaves few warps per SM, so spread them over more blocks
        launcher = launchers[kernel] = runtime.CachedLaunch(kernel, block_dim=64)
    if device.type == "cuda":
        wp = runtime.init()
        torch_stream = torch.cuda.current_stream(device)
        key = (device.index, torch_stream.cuda_stream)
        stream = _STREAMS.get(key)
        if stream is None:
            stream = _STREAMS[key] = wp.stream_from_torch(torch_stream)
        launcher(dim, inputs, warp_device(device), stream)
    else:
        launcher(dim, inputs, "cpu")


def f32(t: torch.Tensor) -> torch.Tensor:
    """float32 view for a kernel argument. Any strides are fine (descriptors carry them): sample-major
    [R, S] tensors (stride 1 along R) give coalesced loads, and broadcast cotangents (stride 0) are read
    without being materialised."""
    return t.detach().to(torch.float32)


def f32v(t: torch.Tensor) -> torch.Tensor:
    """float32 for a vector-element argument ([..., 3]): the last axis must be contiguous."""
    t = t.detach().to(torch.float32)
    return t if t.stride(-1) == 1 else t.contiguous()
