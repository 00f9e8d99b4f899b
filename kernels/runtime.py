"""Warp runtime helpers: lazy init, the kernel cache location, array descriptors, struct values and cached
launches.

Warp is initialised on first use, never at import. The kernel cache goes to $SLWARP_KERNEL_CACHE, else
$WARP_CACHE_PATH, else Warp's default (per user). Kernels are pure functions of their source, so a warm
cache changes only compile time, never results or test order. On a machine without the CUDA driver, Warp's
"Could not find or load the NVIDIA CUDA driver" warning is held back (SLWARP_VERBOSE=1 shows it and Warp's banner).
"""
from __future__ import annotations

import contextlib
import ctypes
import os
import sys
import tempfile
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
            verbose = bool(os.environ.get("SLWARP_VERBOSE"))
            if not verbose:
                wp.config.log_level = 30  # warnings and errors only: no banner, no per-module load lines
            with contextlib.nullcontext() if verbose or _cuda_driver_present() else _without_driver_warning():
                wp.init()
            _ready = True
    return wp


@contextlib.contextmanager
def torch_capture(torch_stream):
    """Tell Warp that `torch_stream` is capturing a CUDA graph that torch began (torch.cuda.graph, thread-local
    mode), for the capture's duration. Why: Warp frees an array's memory when Python drops it, and a free in the
    capturing thread invalidates the capture (Warp CUDA error 900 in release_now), e.g. a simulation's arrays that the
    garbage collector reaches during a warm process's next capture. Told of the capture, Warp defers those frees
    until it ends (H100: a capture with a Warp array dropped inside failed without this and succeeded with it)."""
    wp = init()
    stream = wp.stream_from_torch(torch_stream)
    mode = getattr(getattr(wp, "CaptureMode", None), "THREAD_LOCAL", None)  # the mode training.graph_step captures in
    if mode is None:
        wp.capture_begin(stream=stream, external=True)
    else:
        wp.capture_begin(stream=stream, external=True, capture_mode=mode)
    try:
        yield
    finally:
        try:
            wp.capture_end(stream=stream)  # ends Warp's record of it; torch ends the capture itself
        except RuntimeError:
            pass  # the capture failed: Warp has dropped its record already, and torch reports the failure


# what Warp's native library prints (with fprintf, so Warp's log level does not apply) when it finds no CUDA driver:
# on a CPU-only machine that is expected, not a problem worth a line on every command
DRIVER_WARNING = "Warp CUDA warning: Could not find or load the NVIDIA CUDA driver"


def _cuda_driver_present() -> bool:
    """Whether the CUDA driver library loads, as Warp looks for it (Linux: libcuda.so[.1]; Windows: nvcuda.dll);
    True elsewhere (macOS builds of Warp have no CUDA and print nothing)."""
    names = {"linux": ("libcuda.so", "libcuda.so.1"), "win32": ("nvcuda.dll",)}.get(sys.platform)
    if names is None:
        return True
    for name in names:
        try:
            ctypes.CDLL(name)
            return True
        except OSError:
            pass
    return False


@contextlib.contextmanager
def _without_driver_warning():
    """Native writes to stderr (file descriptor 2) go to a temporary file for the block; afterwards every line but
    Warp's missing-driver warning is written back to stderr."""
    try:
        sys.stderr.flush()
        saved = os.dup(2)
    except (OSError, ValueError, AttributeError):  # no usable stderr descriptor: nothing to hold back
        yield
        return
    with tempfile.TemporaryFile(mode="w+b") as held:
        os.dup2(held.fileno(), 2)
        try:
            yield
        finally:
            with contextlib.suppress(OSError, ValueError):
                sys.stderr.flush()
            os.dup2(saved, 2)
            os.close(saved)
            held.seek(0)
            rest = [line for line in held.read().decode(errors="replace").splitlines(keepends=True)
                    if not line.startswith(DRIVER_WARNING)]
            if rest and sys.stderr is not None:
                sys.stderr.write("".join(rest))
                sys.stderr.flush()


def array_desc(t, vec: int = 0):
    """A Warp array descriptor (wp.from_torch(..., return_ctype=True)) of a torch tensor, without building
    a wp.array: any strides; vec = 0: the tensor's own shape and element type; vec = 2 or 3: the last axis
    (contiguous) becomes a vec2/vec3 element, e.g. [R, S, 3] -> array2d of vec3; any other vec = n: a float32 vector
    of length n (the hash grid's feature vectors). A 0-d tensor is passed as a 1-element array. Kernels accept
    descriptors verbatim."""
    wp = init()
    if t.dim() == 0:
        t = t.reshape(1)
    if vec == 0:
        dtype = None
    else:
        dtype = {2: wp.vec2, 3: wp.vec3}.get(vec) or wp.types.vector(length=vec, dtype=wp.float32)
    return wp.from_torch(t, dtype=dtype, requires_grad=False, return_ctype=True)


def _field_converter(var_type):
    """How `struct_value` turns a value into the ctypes value of one struct field of type var_type."""
    wp = init()
    if wp.types.is_array(var_type):
        n = var_type.dtype._length_ if wp.types.type_is_vector(var_type.dtype) else 0  # 0: the tensor's own dtype
        null = var_type.__ctype__()  # the annotation's descriptor: a null array of the field's shape
        return lambda t: array_desc(t, n) if t is not None else null
    if hasattr(var_type, "ctype") and hasattr(var_type, "vars"):  # a nested struct: its instance or ctypes value
        return lambda v: v.__ctype__() if hasattr(v, "__ctype__") else v
    return lambda v: v


_CONVERTERS: dict = {}


def struct_value(cls, **fields):
    """The ctypes value of Warp struct `cls` (what a kernel takes; `CachedLaunch` passes it as is) from its fields
    by name: torch tensors for array fields (as array descriptors, `array_desc`; a vector element's length comes
    from the field's type; None gives a null array, for a field the kernel does not read), struct instances or
    ctypes values for nested structs, numbers and Warp vectors for the rest. Fields left out are zero."""
    conv = _CONVERTERS.get(cls)
    if conv is None:
        conv = _CONVERTERS[cls] = {name: _field_converter(var.type) for name, var in cls.vars.items()}
    return cls.ctype(**{name: conv[name](v) for name, v in fields.items()})


class CachedLaunch:
    """Launch one kernel repeatedly at a fraction of wp.launch's Python cost.

    The first call records a launch command (wp.launch(record_cmd=True)); later calls only rewrite its
    parameters from ctypes values (array descriptors, struct ctypes values as `struct_value` makes them, struct
    instances, numbers) and relaunch it. Argument lists must keep the same kinds in the same places from call
    to call.
    """

    def __init__(self, kernel, block_dim: int | None = None):
        self.kernel = kernel
        self.block_dim = block_dim
        self._cmds: dict = {}

    def __call__(self, dim, args, device, stream=None):
        wp = init()
        key = str(device)
        entry = self._cmds.get(key)
        if entry is None:
            kw = {"block_dim": self.block_dim} if self.block_dim else {}
            inputs = [self._packable(i, a) for i, a in enumerate(args)]
            cmd = wp.launch(self.kernel, dim=dim, inputs=inputs, device=device, record_cmd=True, **kw)
            self._cmds[key] = [cmd, dim]
        else:
            cmd, last_dim = entry
            if dim != last_dim:
                cmd.set_dim(dim)
                entry[1] = dim
            for i, a in enumerate(args):
                if isinstance(a, (int, float, ctypes.Structure)):  # numbers, array descriptors, struct values
                    cmd.set_param_at_index_from_ctype(i, a)
                elif hasattr(a, "__ctype__") and not hasattr(a, "ptr"):  # a wp.struct instance
                    cmd.set_param_at_index_from_ctype(i, a.__ctype__())
                else:
                    cmd.set_param_at_index(i, a)
        cmd.launch(stream)

    def _packable(self, i: int, a):
        """Argument i as wp.launch packs it: a struct's ctypes value in an object that gives it back (wp.launch
        asks a struct argument for its __ctype__())."""
        if isinstance(a, ctypes.Structure) and not init().types.is_array(self.kernel.adj.args[i].type):
            return _StructValue(a)
        return a


class _StructValue:
    """A struct's ctypes value as wp.launch takes a struct argument (it only asks for __ctype__(); a struct's own
    instance type is not built from a ctypes value the same way in every Warp version)."""

    __slots__ = ("value",)

    def __init__(self, value):
        self.value = value

    def __ctype__(self):
        return self.value
