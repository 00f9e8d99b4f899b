"""The image files of a scan: camera images, patterns, masks (PNG/TIFF, 8- or 16-bit or float, colour read as gray)
and depth maps (.npy float mm, or 16-bit PNG in 0.1 mm, 0 = invalid). Bad files raise ScanError naming them."""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from .errors import ScanError

__all__ = ["IMAGE_SIGNATURES", "read_image", "write_image", "read_depth", "read_mask", "read_image_stack"]

# the first bytes of the image files slwarp reads: PNG, TIFF and BigTIFF (either byte order)
IMAGE_SIGNATURES = (b"\x89PNG", b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+")


def _check_image_file(path: Path, what: str) -> None:
    """ScanError unless `path` is a regular file that starts as a PNG or TIFF does. Why: OpenCV picks its decoder
    from the content, whatever the name; the contract's two formats keep its other decoders (JPEG, WebP, ...) away
    from files that others wrote."""
    if not path.is_file():
        raise ScanError(f"{what} not found: {path}")
    with open(path, "rb") as f:
        head = f.read(4)
    if not head.startswith(IMAGE_SIGNATURES):
        raise ScanError(f"{what} is unreadable or corrupt (not a PNG or TIFF file: slwarp reads those two formats): {path}")


def read_image(path: str | os.PathLike, what: str = "image") -> np.ndarray:
    """Read an 8/16-bit or float PNG/TIFF as float32 gray in [0, 1] (colour converted to gray)."""
    import cv2

    path = Path(path)
    _check_image_file(path, what)
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise ScanError(f"{what} is unreadable or corrupt (not a PNG/TIFF image OpenCV can decode): {path}")
    if img.ndim == 3:
        if img.shape[2] == 4:
            img = cv2.cvtColor(img, cv2.COLOR_BGRA2GRAY)
        elif img.shape[2] == 3:
            img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
        elif img.shape[2] == 1:
            img = img[..., 0]
        else:
            raise ScanError(f"{what} has {img.shape[2]} channels (need gray, BGR or BGRA): {path}")
    if img.dtype == np.uint8:
        return img.astype(np.float32) / 255.0
    if img.dtype == np.uint16:
        return img.astype(np.float32) / 65535.0
    if img.dtype in (np.float32, np.float64):
        out = img.astype(np.float32)
        if not np.all(np.isfinite(out)):
            raise ScanError(f"{what} holds non-finite values: {path}")
        return out
    raise ScanError(f"{what} has unsupported pixel type {img.dtype} (need 8- or 16-bit or float): {path}")


def write_image(path: Path, img: np.ndarray, bits: int = 8) -> None:
    """Write float [0, 1] gray as an 8- or 16-bit PNG."""
    import cv2

    scale = 255 if bits == 8 else 65535
    dtype = np.uint8 if bits == 8 else np.uint16
    q = np.clip(np.rint(np.asarray(img, np.float64) * scale), 0, scale).astype(dtype)
    if not cv2.imwrite(str(path), q):
        raise ScanError(f"could not write image: {path}")


def read_depth(path: str | os.PathLike, what: str = "depth") -> np.ndarray:
    """Depth map in mm, float32, NaN invalid: a .npy (float, mm) or 16-bit PNG (0.1 mm, 0 invalid)."""
    import cv2

    path = Path(path)
    if not path.is_file():
        raise ScanError(f"{what} not found: {path}")
    if path.suffix.lower() == ".npy":
        try:
            d = np.load(path, allow_pickle=False)  # an object array would unpickle its items: refused
        except Exception as e:  # noqa: BLE001 - any numpy failure is a corrupt file for the user
            raise ScanError(f"{what} is not a readable .npy array ({' '.join(str(e).split())}): {path}") from None
        if not isinstance(d, np.ndarray):
            d.close()
            raise ScanError(f"{what} is an .npz archive, not a .npy array: {path}")
        if d.dtype.kind not in "biuf":
            raise ScanError(f"{what} holds {d.dtype} values, not numbers (need float, mm): {path}")
        d = d.astype(np.float32)
        if d.ndim != 2:
            raise ScanError(f"{what} must be a 2-D array, got shape {d.shape}: {path}")
        d[~np.isfinite(d) | (d <= 0)] = np.nan
        return d
    _check_image_file(path, what)
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise ScanError(f"{what} is unreadable or corrupt: {path}")
    if img.ndim != 2 or img.dtype != np.uint16:
        raise ScanError(f"{what} PNG must be single-channel 16-bit (depth in 0.1 mm), got {img.dtype} {img.shape}: {path}")
    d = img.astype(np.float32) / 10.0
    d[img == 0] = np.nan
    return d


def read_mask(path: Path) -> np.ndarray:
    """A mask image as bool [H, W]: set where brighter than half scale."""
    return read_image(path, "mask") > 0.5


def read_image_stack(files: list[tuple[Path, str]], shape: tuple[int, int], kind: str, size_name: str) -> np.ndarray:
    """Read images of one kind and check their size against `shape` (height, width)."""
    out = np.empty((len(files), *shape), np.float32)
    for i, (f, what) in enumerate(files):
        img = read_image(f, what)
        if img.shape != shape:
            raise ScanError(
                f"{kind} size {img.shape[1]}x{img.shape[0]} != {size_name} size {shape[1]}x{shape[0]}: {f}"
            )
        out[i] = img
    return out
