"""Training checkpoints: what a run's checkpoint holds, writing and reading it, and the run identity a resumed run
must match.

    state = make_state(iteration=..., config=cfg, ...)   # Trainer.state
    write_checkpoint(state, path)                         # atomic: a temporary file, then a rename
    ck = read_checkpoint(path, map_location=device)       # CheckpointError naming the file and the problem
    check_field(ck, cfg.field.network(), path)            # the same network as the config asks for
    restore(ck, path, field=..., variance=..., optimizer=..., generator=..., pixels=H * W)

A checkpoint (torch's zip format) holds tensors and plain data only: dicts, lists, str, int, float, bool and None.
The config is `TrainConfig.to_dict()`, the history lists, the run identity plain values, the random generator's
state a uint8 tensor. `read_checkpoint` reads it with `torch.load(weights_only=True)`, whose unpickler builds those
types and refuses any other before building anything, so a checkpoint from someone else can fail to load but never
runs code; a file that is not a zip archive is refused before torch reads it. Checkpoints have a format number
(`FORMAT`, key "format"); those written before it (format 1) hold the same types and load the same way.

Identity: a checkpoint records `run_identity` (the frames by name and content digest, the depth range, a digest of
the calibration and every option that is not `resumable`); `identity_differences` lists what changed, which
`RunMismatch` reports on --resume. A new run refuses to replace an existing checkpoint (`CheckpointExists`).
"""
from __future__ import annotations

import hashlib
import json
import os
import pickle
import re
import zipfile
from pathlib import Path

import numpy as np
import torch

__all__ = ["FORMAT", "CheckpointError", "CheckpointExists", "RunMismatch", "run_identity", "identity_differences",
           "make_state", "write_checkpoint", "read_checkpoint", "check_field", "restore"]

# 2: the "format" key, every entry a tensor or plain data (checked on writing). 1: no key (the same types in practice)
FORMAT = 2
# what a checkpoint must hold, and of which type (`read_checkpoint` refuses another)
REQUIRED = {"iteration": int, "config": dict, "field": dict, "variance": dict, "optimizer": dict,
            "generator": torch.Tensor, "n_frames": int, "history": dict}
# what it may hold (older checkpoints lack some), and of which type
OPTIONAL = {"format": int, "identity": dict, "elapsed": (int, float), "init_depth": (torch.Tensor, type(None)),
            "pattern_blur": (int, float), "volume": dict, "depth_range": (list, tuple)}
_PLAIN = (str, int, float, bool, type(None))
AGAIN = "start again with --overwrite"


class CheckpointError(ValueError):
    """A checkpoint that cannot be used: missing, truncated, not a slwarp checkpoint, or of another run."""


class CheckpointExists(CheckpointError):
    """A new run would replace an existing checkpoint (pass resume=True to continue it, overwrite=True to replace it)."""


class RunMismatch(CheckpointError):
    """--resume with a checkpoint written by a different run; `differences` lists (what, old, new)."""

    def __init__(self, path, differences: list[tuple[str, object, object]]):
        self.differences = differences
        lines = "; ".join(f"{what}: {old} in the checkpoint, {new} now" for what, old, new in differences)
        super().__init__(f"{path}: --resume with a different run ({lines}); resume with the same scan, frames and "
                         "options, or start again with --overwrite (or another --out)")


# --- identity ---------------------------------------------------------------------------------


def _digest(*arrays) -> str:
    h = hashlib.sha256()
    for a in arrays:
        a = np.ascontiguousarray(a)
        h.update(str((a.dtype.str, a.shape)).encode())
        h.update(a.tobytes())
    return h.hexdigest()[:16]


def run_identity(scan, config, depth_range) -> dict:
    """What defines a run's result, as its checkpoint records it: the frames (name and a digest of the image and
    pattern, in order), the depth range (mm), a digest of the calibration and every option a resumed run must
    keep (`TrainConfig.fixed_options`). Plain values (JSON-able)."""
    calib = json.dumps({"camera": scan.camera.to_dict(), "projector": scan.projector.to_dict(),
                        "R": np.asarray(scan.projector.R).tolist(), "T": np.asarray(scan.projector.T).tolist()},
                       sort_keys=True)
    return {"frames": [[name, _digest(scan.images[i], scan.patterns[i])] for i, name in enumerate(scan.names)],
            "depth_range": [float(x) for x in depth_range],
            "calibration": hashlib.sha256(calib.encode()).hexdigest()[:16],
            "options": config.fixed_options()}


def _short_list(names: list[str], limit: int = 6) -> str:
    return ", ".join(names[:limit]) + (f", ... ({len(names)} in all)" if len(names) > limit else "")


def identity_differences(old: dict, new: dict) -> list[tuple[str, object, object]]:
    """(what, old value, new value) for every difference between two `run_identity` records."""
    diffs = []
    old_frames, new_frames = [tuple(f) for f in old["frames"]], [tuple(f) for f in new["frames"]]
    if old_frames != new_frames:
        old_names, new_names = [f[0] for f in old_frames], [f[0] for f in new_frames]
        if old_names != new_names:
            diffs.append(("frames", f"{len(old_names)} ({_short_list(old_names)})",
                          f"{len(new_names)} ({_short_list(new_names)})"))
        else:
            changed = [o[0] for o, n in zip(old_frames, new_frames) if o[1] != n[1]]
            diffs.append(("frame content", "other images or patterns", f"changed in {_short_list(changed)}"))
    if [float(x) for x in old["depth_range"]] != [float(x) for x in new["depth_range"]]:
        diffs.append(("depth range (mm)", tuple(old["depth_range"]), tuple(new["depth_range"])))
    if old["calibration"] != new["calibration"]:
        diffs.append(("calibration", "digest " + old["calibration"], "digest " + new["calibration"]))
    for name in sorted(set(old["options"]) | set(new["options"])):
        a, b = old["options"].get(name, "(absent)"), new["options"].get(name, "(absent)")
        if a != b:
            diffs.append((f"option {name}", a, b))
    return diffs


# --- writing ----------------------------------------------------------------------------------


def _check_plain(value, where: str) -> None:
    """TypeError naming the entry when `value` holds anything but tensors and plain data (exact types: a numpy
    float is a float subclass, and torch.load(weights_only=True) would refuse it)."""
    if isinstance(value, torch.Tensor) or type(value) in _PLAIN:
        return
    if isinstance(value, dict):  # OrderedDict too (state dicts): weights_only reads it
        for k, v in value.items():
            if type(k) not in (str, int):
                raise TypeError(f"checkpoint entry {where} has a key of type {type(k).__name__}: only str and int keys")
            _check_plain(v, f"{where}[{k!r}]")
        return
    if type(value) in (list, tuple):
        for i, v in enumerate(value):
            _check_plain(v, f"{where}[{i}]")
        return
    raise TypeError(f"checkpoint entry {where} is a {type(value).__module__}.{type(value).__qualname__}: a checkpoint "
                    "holds tensors and plain data only")


def make_state(*, iteration: int, config: dict, field: torch.nn.Module, variance: torch.nn.Module, optimizer,
               generator_state: torch.Tensor, n_frames: int, volume: dict, depth_range, history: dict,
               elapsed: float, init_depth: torch.Tensor | None, pattern_blur: float, identity: dict,
               pattern_halo: float = 0.0) -> dict:
    """A checkpoint's contents: the config as `TrainConfig.to_dict()`, the volume and history as dicts, the
    generator's state after the steps taken (a uint8 tensor). TypeError when anything is not a tensor or plain
    data (a bug: such a checkpoint could not be read back)."""
    state = {
        "format": FORMAT,
        "iteration": int(iteration),
        "config": config,
        "field": field.state_dict(),
        "variance": variance.state_dict(),
        "optimizer": optimizer.state_dict(),
        "generator": generator_state.detach().to("cpu", torch.uint8),
        "n_frames": int(n_frames),
        "volume": {k: [float(x) for x in v] for k, v in volume.items()},
        "depth_range": [float(x) for x in depth_range],
        "history": history,
        "elapsed": float(elapsed),
        "init_depth": init_depth,
        "pattern_blur": float(pattern_blur),
        "pattern_halo": float(pattern_halo),  # the lens halo's share the run trains with (fitted or given)
        "identity": identity,
    }
    _check_plain(state, "state")
    return state


def write_checkpoint(state: dict, path) -> Path:
    """Atomically write `state` to `path` (write to a temporary file, then rename); OSError naming the file."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp")
    try:
        torch.save(state, tmp)
        os.replace(tmp, path)
    except (OSError, RuntimeError) as e:  # torch reports a full disk as a RuntimeError of its zip writer
        tmp.unlink(missing_ok=True)
        if isinstance(e, OSError):
            raise
        raise OSError(f"{path}: could not write the checkpoint ({str(e).splitlines()[0]}); is the disk full?") from None
    return path


# --- reading ----------------------------------------------------------------------------------


def _refused_global(error: Exception) -> str | None:
    """The type or function the weights-only unpickler refused (e.g. posix.system, io.open), from its message."""
    m = re.search(r"GLOBAL ([\w.]+)", str(error))
    return m[1] if m else None


def _first_line(error: Exception) -> str:
    lines = [ln.strip() for ln in str(error).splitlines() if ln.strip()]
    return f"{type(error).__name__}: {lines[0]}" if lines else type(error).__name__


def read_checkpoint(path, map_location="cpu") -> dict:
    """The checkpoint at `path`, read with torch.load(weights_only=True): tensors and plain data only, nothing
    unpickled that could run code. CheckpointError naming the path and the problem (missing, truncated, not a
    slwarp checkpoint, holding other types, of a newer format), one line."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"{path}: no checkpoint to resume from (run without --resume to start)")
    # slwarp writes torch's zip format only: anything else (empty, truncated, torch's legacy format, a bare
    # pickle) is refused before torch reads it
    if not zipfile.is_zipfile(path):
        raise CheckpointError(f"{path}: not a readable checkpoint (not a torch zip archive: empty, truncated or "
                              f"another kind of file); {AGAIN}")
    try:
        ck = torch.load(path, map_location=map_location, weights_only=True)
    except pickle.UnpicklingError as e:
        refused = _refused_global(e)
        if refused is None:
            raise CheckpointError(f"{path}: not a readable checkpoint ({_first_line(e)}); {AGAIN}") from None
        raise CheckpointError(f"{path}: refused unread: it refers to {refused}, and a slwarp checkpoint holds "
                              f"tensors and plain data only (not written by slwarp, or altered); {AGAIN}") from None
    except Exception as e:  # noqa: BLE001 - torch reports a damaged archive as many types (zip, EOF, runtime)
        raise CheckpointError(f"{path}: not a readable checkpoint ({_first_line(e)}); {AGAIN}") from None
    if not isinstance(ck, dict) or any(k not in ck for k in REQUIRED):
        missing = [k for k in REQUIRED if not isinstance(ck, dict) or k not in ck]
        raise CheckpointError(f"{path}: not a slwarp training checkpoint (missing {missing}); {AGAIN}")
    fmt = ck.get("format", 1)
    if type(fmt) is int and fmt > FORMAT:
        raise CheckpointError(f"{path}: written by a newer slwarp (checkpoint format {fmt}, this one reads up to "
                              f"{FORMAT}); resume it with that version, or {AGAIN}")
    for key, kind in {**REQUIRED, **OPTIONAL}.items():
        if key in ck and not isinstance(ck[key], kind):
            raise CheckpointError(f"{path}: not a slwarp training checkpoint (entry {key!r} is a "
                                  f"{type(ck[key]).__name__}); {AGAIN}")
    if ck["generator"].dtype != torch.uint8 or not all(isinstance(v, list) for v in ck["history"].values()):
        raise CheckpointError(f"{path}: not a slwarp training checkpoint (a malformed generator state or history); {AGAIN}")
    if "identity" in ck and not _is_identity(ck["identity"]):
        raise CheckpointError(f"{path}: not a slwarp training checkpoint (a malformed run identity); {AGAIN}")
    return ck


def _is_identity(doc: dict) -> bool:
    """Whether `doc` has the shape of a `run_identity` record (what `identity_differences` reads)."""
    frames, depth_range = doc.get("frames"), doc.get("depth_range")
    return (isinstance(frames, list) and all(isinstance(f, (list, tuple)) and len(f) == 2 for f in frames)
            and isinstance(depth_range, (list, tuple)) and len(depth_range) == 2
            and all(type(x) in (int, float) for x in depth_range)
            and isinstance(doc.get("calibration"), str) and isinstance(doc.get("options"), dict))


def check_field(ck: dict, network: dict, path) -> None:
    """CheckpointError unless the checkpoint's field is the network `network` (`FieldConfig.network()`: its kind and
    the options that define it)."""
    saved = ck["config"].get("field", ck["config"])  # flat in checkpoints written before the config had sections
    if not isinstance(saved, dict):
        raise CheckpointError(f"{path}: not a slwarp training checkpoint (its config has no field section); {AGAIN}")
    saved_kind = saved.get("kind", "mlp")  # written before the hash grid: the MLP
    if saved_kind != network["kind"]:
        raise CheckpointError(f"{path}: checkpoint was trained with the {saved_kind} field, the config asks for the "
                              f"{network['kind']} field (--field); resume with --field {saved_kind} and the same preset")
    differ = {k: (saved.get(k), v) for k, v in network.items() if saved.get(k) != v}
    if differ:
        raise CheckpointError(f"{path}: checkpoint was trained with a different {saved_kind} field (checkpoint, config: "
                              + ", ".join(f"{k} {a!r} vs {b!r}" for k, (a, b) in differ.items())
                              + "); use the same preset/options to resume")


def restore(ck: dict, path, *, field: torch.nn.Module, variance: torch.nn.Module, optimizer,
            generator: torch.Generator, pixels: int) -> None:
    """Load the checkpoint's weights, Adam's state and the generator's state into these; CheckpointError when they
    do not fit (a checkpoint altered by hand, or of a field these options do not build). pixels: the camera's
    pixel count, the size of a starting depth map."""
    init_depth = ck.get("init_depth")
    if init_depth is not None and init_depth.numel() != pixels:
        raise CheckpointError(f"{path}: its starting depth map has {init_depth.numel()} pixels, the camera "
                              f"{pixels}; {AGAIN}")
    try:
        field.load_state_dict(ck["field"])
        variance.load_state_dict(ck["variance"])
        optimizer.load_state_dict(ck["optimizer"])
        # a CPU generator takes a CPU state only: map_location may have moved it to the GPU
        generator.set_state(ck["generator"].to("cpu"))
    except (RuntimeError, ValueError, KeyError, TypeError, IndexError) as e:
        raise CheckpointError(f"{path}: does not fit this run's field and optimizer ({_first_line(e)}); "
                              f"{AGAIN}") from None
