"""Output writers: depth maps and point clouds/meshes, the files every reconstruction method leaves.

    write_depth(folder, depth)           depth.npy (float32 mm, NaN invalid) + depth.png (uint16, 0.1 mm, 0 invalid)
    write_confidence(folder, conf)       confidence.npy (float32 in [0, 1], higher = more trusted, NaN where no depth);
                                         read_confidence reads it back, checked
    write_depth_png(path, depth)         the 16-bit PNG alone (the authors' depth format; read back by
                                         slwarp.scans.scan.read_depth)
    write_points_ply(path, points, ...)  the finite points of a point map as a binary PLY, gray or RGB
    write_mesh_ply(path, mesh)           a triangle mesh (vertices, faces) as a binary PLY
    check_output_folder(path)            OutputError unless `path` can be (or is) a folder: not a file, nor under one
    with staged_outputs(folder) as tmp:  write a run's outputs into `tmp`; they appear in `folder` together on
        ...                              success, and not at all on failure

Colour pictures (depth, error maps, previews) are in slwarp.evaluation.viz.
"""
from __future__ import annotations

import contextlib
import os
import shutil
from pathlib import Path

import numpy as np

__all__ = ["write_depth", "write_depth_png", "write_points_ply", "write_mesh_ply", "write_confidence", "read_confidence",
           "OutputError", "check_output_folder", "staged_outputs"]


class OutputError(OSError):
    """An output folder that cannot be written: the path is a file or lies under one."""


def check_output_folder(path: str | os.PathLike) -> Path:
    """`path` as a Path, after checking that it is a folder or can become one (no file at it or above it);
    OutputError names the file in the way. Permissions and free space show when writing (OSError)."""
    path = Path(path)
    for p in (path, *path.parents):
        if p.exists():
            if not p.is_dir():
                raise OutputError(f"{path}: output folder " + ("is a file" if p == path else f"lies under a file ({p})"))
            break
    return path


@contextlib.contextmanager
def staged_outputs(folder: str | os.PathLike, keep: tuple[str, ...] = ("train",)):
    """Write a run's outputs into a temporary folder beside `folder` (yielded), then move them into `folder`
    together: when `folder` does not exist it is one rename; otherwise the previous outputs (every entry but
    those named in `keep`, e.g. the training checkpoint) are replaced by the new ones. On an exception nothing
    of this run appears, the temporary folder is removed, and so is `folder` if this call created it and it is
    empty (then the exception propagates)."""
    folder = check_output_folder(folder)
    existed = folder.exists()
    folder.parent.mkdir(parents=True, exist_ok=True)
    staging = folder.parent / f".{folder.name}.partial-{os.getpid()}"
    shutil.rmtree(staging, ignore_errors=True)
    staging.mkdir()
    try:
        try:
            yield staging
        except OSError as e:
            if e.filename is None and e.errno:  # some writers (numpy, matplotlib) do not name the file
                raise OSError(e.errno, f"{e.strerror} (writing the outputs of {folder})") from e
            raise
        if not folder.exists():
            os.replace(staging, folder)
            return
        old = folder.parent / f".{folder.name}.previous-{os.getpid()}"
        shutil.rmtree(old, ignore_errors=True)
        old.mkdir()
        for entry in folder.iterdir():
            if entry.name not in keep:
                os.replace(entry, old / entry.name)
        for entry in staging.iterdir():
            if (folder / entry.name).is_dir():  # a kept folder the run also wrote into: replace it whole
                os.replace(folder / entry.name, old / entry.name)
            os.replace(entry, folder / entry.name)
        shutil.rmtree(old, ignore_errors=True)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
        if not existed and folder.is_dir():  # e.g. a train/ folder whose first checkpoint could not be written
            for sub in sorted(folder.rglob("*"), key=lambda q: len(q.parts), reverse=True):
                if sub.is_dir() and not any(sub.iterdir()):
                    sub.rmdir()
            if not any(folder.iterdir()):
                folder.rmdir()

DEPTH_PNG_PER_MM = 10.0  # depth PNG counts per mm: one count is 0.1 mm (max 6553.5 mm); 0 marks an invalid pixel


def write_depth_png(path: str | os.PathLike, depth: np.ndarray) -> None:
    """Write depth (mm, NaN invalid) as a 16-bit PNG in 0.1 mm units, 0 = invalid."""
    import cv2

    d = np.asarray(depth, np.float64)
    q = np.where(np.isfinite(d) & (d > 0), np.clip(np.rint(d * DEPTH_PNG_PER_MM), 1, 65535), 0).astype(np.uint16)
    if not cv2.imwrite(str(path), q):
        raise OSError(f"could not write depth PNG: {path}")


def write_depth(folder: str | os.PathLike, depth: np.ndarray) -> None:
    """depth.npy (float32 mm, NaN invalid) and depth.png (uint16, 0.1 mm, 0 invalid) in `folder`."""
    folder = Path(folder)
    np.save(folder / "depth.npy", np.asarray(depth).astype(np.float32))
    write_depth_png(folder / "depth.png", depth)


def _write_ply(path: str | os.PathLike, vertices: np.ndarray, vertex_props: list[tuple[str, str]],
               faces: np.ndarray | None = None) -> None:
    """A binary little-endian PLY: `vertices` a structured array whose fields are `vertex_props` (name, PLY type),
    and triangle `faces` [F, 3] (int) when given. Written with numpy (trimesh's exporter cost a fresh process about
    half a second of imports)."""
    header = ["ply", "format binary_little_endian 1.0", "comment slwarp", f"element vertex {len(vertices)}"]
    header += [f"property {t} {n}" for n, t in vertex_props]
    if faces is not None:
        header += [f"element face {len(faces)}", "property list uchar int vertex_indices"]
    header.append("end_header")
    with open(path, "wb") as f:
        f.write(("\n".join(header) + "\n").encode("ascii"))
        f.write(vertices.tobytes())
        if faces is not None:
            rec = np.empty(len(faces), dtype=[("n", "u1"), ("v", "<i4", (3,))])
            rec["n"] = 3
            rec["v"] = faces
            f.write(rec.tobytes())


def write_points_ply(path: str | os.PathLike, points: np.ndarray, colors: np.ndarray | None = None) -> int:
    """Write the finite points of points [..., 3] (mm) as a binary little-endian PLY (float32 x, y, z); colors
    [...] gray or [..., 3] RGB, in [0, 1] (rounded to 8 bits) or uint8, optional (written as RGBA, alpha 255).
    Returns the number of points written."""
    pts = np.asarray(points, np.float64).reshape(-1, 3)
    keep = np.isfinite(pts).all(1)
    props = [("x", "float"), ("y", "float"), ("z", "float")]
    rgba = None
    if colors is not None:
        c = np.asarray(colors)
        c = c.reshape(-1, 3) if c.ndim >= 2 and c.shape[-1] == 3 and c.size == 3 * keep.size else c.reshape(-1, 1)
        if c.shape[0] != keep.size:
            raise ValueError(f"colors hold {c.shape[0]} entries for {keep.size} points")
        if c.dtype != np.uint8:
            c = np.clip(np.rint(np.asarray(c, np.float64) * 255), 0, 255).astype(np.uint8)
        rgb = np.repeat(c, 3, axis=1) if c.shape[1] == 1 else c
        rgba = np.concatenate([rgb, np.full((len(rgb), 1), 255, np.uint8)], 1)[keep]
        props += [("red", "uchar"), ("green", "uchar"), ("blue", "uchar"), ("alpha", "uchar")]
    n = int(keep.sum())
    v = np.empty(n, dtype=[("xyz", "<f4", (3,))] + ([("rgba", "u1", (4,))] if rgba is not None else []))
    v["xyz"] = pts[keep]
    if rgba is not None:
        v["rgba"] = rgba
    _write_ply(path, v, props)
    return n


def write_mesh_ply(path: str | os.PathLike, mesh) -> None:
    """Write a triangle mesh (mm; anything with `vertices` [V, 3] and `faces` [F, 3], e.g. a trimesh mesh) as a
    binary little-endian PLY (float32 vertices)."""
    verts = np.asarray(mesh.vertices, np.float32).reshape(-1, 3)
    faces = np.asarray(mesh.faces).reshape(-1, 3)
    v = np.empty(len(verts), dtype=[("xyz", "<f4", (3,))])
    v["xyz"] = verts
    _write_ply(path, v, [("x", "float"), ("y", "float"), ("z", "float")], faces)


def write_confidence(folder: str | os.PathLike, confidence: np.ndarray) -> None:
    """confidence.npy in `folder`: the per-pixel confidence [H, W] of the depth map beside it (float32 in [0, 1],
    higher = more trusted, NaN where there is no depth). Its picture: slwarp.evaluation.viz.save_confidence_map."""
    np.save(Path(folder) / "confidence.npy", np.asarray(confidence).astype(np.float32))


def read_confidence(path: str | os.PathLike, shape: tuple[int, int] | None = None) -> np.ndarray:
    """A confidence map [H, W] (float64) from a .npy file; raises ValueError naming the file when it is not a
    2-D array of numbers, not of `shape` (when given), or holds finite values outside [0, 1]."""
    path = Path(path)
    if path.suffix.lower() != ".npy":
        raise ValueError(f"{path}: a confidence map is read from .npy (confidence.png is only its picture)")
    if not path.is_file():
        raise FileNotFoundError(f"confidence map not found: {path}")
    try:
        c = np.load(path, allow_pickle=False)
    except ValueError as e:
        raise ValueError(f"{path}: not a numpy array file ({e})") from None
    if c.ndim != 2 or not np.issubdtype(c.dtype, np.number):
        raise ValueError(f"{path}: a confidence map is a 2-D array of numbers, got {c.dtype} {c.shape}")
    if shape is not None and c.shape != tuple(shape):
        raise ValueError(f"{path}: confidence map is {c.shape[1]}x{c.shape[0]}, the depth map is {shape[1]}x{shape[0]}")
    c = c.astype(np.float64)
    fin = c[np.isfinite(c)]
    if fin.size and (fin.min() < 0 or fin.max() > 1):
        raise ValueError(f"{path}: confidence values must lie in [0, 1], found {fin.min():g} .. {fin.max():g}")
    return c
