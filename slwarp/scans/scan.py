"""Scan: a calibrated camera + projector rig and its frames (captured image + projected pattern).

On disk, the native layout is a folder holding `scan.yaml` (see `Scan.save`), the images and patterns
(PNG/TIFF, 8- or 16-bit, colour converted to gray) and optionally `gt_depth` (.npy float32 mm, or 16-bit
PNG in 0.1 mm, 0 = invalid) and `mask`. `load_scan` also imports the authors' NeSS layout (config.ini)
and the procam-calibration layout (calibration_result.xml + capture_N/ + graycode_pattern/).

In memory: images [N, H, W] and patterns [N, Hp, Wp] float32 in [0, 1]; gt_depth [H, W] float32 mm with
NaN where invalid; mask [H, W] bool. Each frame has a role (`slwarp.scans.roles`: declared in scan.yaml,
mapped from the NeSS tags, or read from slwarp's frame names), resolved once when the Scan is built; the
decoders read roles, never names. Bad input raises `ScanError` naming the file and the problem.

Confinement: every file a scan brings (scan.yaml's frames, gt_depth and mask; an importer's files) is read from
inside the scan folder, links followed (`inside_folder`); a path that leads out of it is refused, naming the entry,
unless allowed: `load_scan(..., outside_paths=True)` (CLI --allow-outside-paths) or `allow_outside_paths: true` in
scan.yaml, which `outside_paths=False` (--no-allow-outside-paths) overrides for scans from others (docs/inputs.md).
"""
from __future__ import annotations

import configparser
import fnmatch
import math
import os
import re
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from ..evaluation.outputs import write_depth_png
from .roles import FrameRole, RoleError, parse_role, parse_selector, resolve_roles, role_groups
from .scanner import CalibrationError, Camera, Projector, check_rotation

__all__ = ["Scan", "ScanError", "load_scan", "read_image", "read_depth", "inside_folder"]

SCAN_FILE = "scan.yaml"
OUTSIDE_FLAG = "allow_outside_paths"  # the scan.yaml key that lets its entries name files outside the folder


class ScanError(ValueError):
    """A scan on disk (or in memory) that cannot be used: the message names the file and the problem."""


# ----------------------------------------------------------------------------------------------
# image I/O


BLACK_LEVEL = 0.02  # full scale: a pixel below it counts as black
SATURATED_LEVEL = 0.99  # full scale: a pixel at or above it counts as saturated
WEAK_PATTERN_SPAN = 0.75  # a non-constant pattern spanning less (max - min, full scale) leaves little contrast


def _names(names: list[str], limit: int = 6) -> str:
    return ", ".join(names[:limit]) + (f", ... ({len(names)} in all)" if len(names) > limit else "")


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


def _read_mask(path: Path) -> np.ndarray:
    return read_image(path, "mask") > 0.5


# ----------------------------------------------------------------------------------------------


@dataclass
class Scan:
    """A calibrated rig and its frames.

    camera, projector: the rig (X_p = R X_c + T, mm); images [N, H, W] and patterns [N, Hp, Wp] float32 in
    [0, 1]; names: one frame name per pair; depth_range: (near, far) mm or None; gt_depth [H, W] mm (NaN
    invalid) or None; mask [H, W] bool or None; source: where it was loaded from.
    declared_roles: frame name -> declared role (a FrameRole, a scan.yaml mapping or a role string; see
    `slwarp.scans.roles`); frames not in it take the role their name gives (or none).
    roles: [N] the resolved FrameRole of each frame (None: no role), set on construction.
    """

    camera: Camera
    projector: Projector
    images: np.ndarray
    patterns: np.ndarray
    names: list[str]
    depth_range: tuple[float, float] | None = None
    gt_depth: np.ndarray | None = None
    mask: np.ndarray | None = None
    source: str | None = None
    meta: dict = field(default_factory=dict)
    declared_roles: dict | None = None
    roles: list = field(init=False, repr=False, compare=False)

    def __post_init__(self):
        self.images = np.asarray(self.images, np.float32)
        self.patterns = np.asarray(self.patterns, np.float32)
        self.names = [str(n) for n in self.names]
        self.validate()
        try:
            self.roles = resolve_roles(self.names, self.declared_roles)
        except RoleError as e:
            raise ScanError(f"{self.source or 'scan'}: {e}") from None

    # --- validation ---------------------------------------------------------------------------
    def validate(self) -> None:
        where = self.source or "scan"
        n = len(self.names)
        if n == 0:
            raise ScanError(f"{where}: the frame list is empty")
        if self.images.ndim != 3 or self.images.shape[0] != n:
            raise ScanError(f"{where}: {self.images.shape[0] if self.images.ndim == 3 else '?'} images for {n} frames")
        if self.patterns.ndim != 3 or self.patterns.shape[0] != n:
            raise ScanError(f"{where}: image count ({n}) != pattern count ({self.patterns.shape[0]})")
        if self.images.shape[1:] != (self.camera.height, self.camera.width):
            raise ScanError(
                f"{where}: image size {self.images.shape[2]}x{self.images.shape[1]} != camera size "
                f"{self.camera.width}x{self.camera.height}"
            )
        if self.patterns.shape[1:] != (self.projector.height, self.projector.width):
            raise ScanError(
                f"{where}: pattern size {self.patterns.shape[2]}x{self.patterns.shape[1]} != projector size "
                f"{self.projector.width}x{self.projector.height}"
            )
        if len(set(self.names)) != n:
            dup = sorted({x for x in self.names if self.names.count(x) > 1})
            raise ScanError(f"{where}: duplicate frame names {dup}")
        if self.depth_range is not None:
            near, far = (float(x) for x in self.depth_range)
            if not (math.isfinite(near) and math.isfinite(far) and 0 < near < far):
                raise ScanError(f"{where}: depth_range must be 0 < near < far (mm), got {self.depth_range}")
            self.depth_range = (near, far)
        for name, arr in (("gt_depth", self.gt_depth), ("mask", self.mask)):
            if arr is not None and arr.shape != (self.camera.height, self.camera.width):
                raise ScanError(f"{where}: {name} shape {arr.shape} != camera size {self.camera.height}x{self.camera.width}")

    def problems(self, contrast: float = 0.05) -> list[str]:
        """What makes this scan unusable or suspect, one sentence each naming the frames: too few frames, black
        or saturated frames, no pixel with contrast (a modulation max - min above `contrast`, full scale) and
        patterns with almost no contrast (e.g. a colour pattern drawn in one channel, read as gray). Empty when
        none. `slwarp info` prints them as warnings; the trainer and the decoders name them when they fail."""
        out = []
        n = len(self.names)
        if n < 2:
            out.append(f"only {n} frame ({', '.join(self.names)}): a + b P(x) has two unknowns per pixel, the neural "
                       "method and the decoders need at least 2 frames")
        img = self.images
        dark_pattern = self.patterns.max(axis=(1, 2)) <= 0  # a "black" frame (projector off) may well be black
        black = [nm for nm, im, off in zip(self.names, img, dark_pattern)
                 if not off and float(np.mean(im < BLACK_LEVEL)) > 0.99]
        if black:
            out.append(f"{'all frames are' if len(black) == n else f'{len(black)} of {n} frames are'} black (over 99% "
                       f"of pixels below {BLACK_LEVEL:.0%} of full scale): {_names(black)}; check exposure and projector")
        saturated = [nm for nm, im in zip(self.names, img) if float(np.mean(im >= SATURATED_LEVEL)) > 0.5]
        if saturated:
            out.append(f"{'all frames are' if len(saturated) == n else f'{len(saturated)} of {n} frames are'} saturated "
                       f"(over half the pixels at {SATURATED_LEVEL:.0%} of full scale or more): {_names(saturated)}; "
                       "lower the exposure")
        if n >= 2 and not (img.max(0) - img.min(0) > contrast).any():
            out.append(f"no pixel changes by more than {contrast:g} of full scale across the {n} frames: the patterns "
                       "leave no contrast in the images")
        span = self.patterns.max(axis=(1, 2)) - self.patterns.min(axis=(1, 2))
        weak = [nm for nm, sp in zip(self.names, span) if 0 < sp < WEAK_PATTERN_SPAN]
        if weak:
            out.append(f"pattern{'s' if len(weak) > 1 else ''} {_names(weak)} span{'' if len(weak) > 1 else 's'} only "
                       f"{float(span[self.names.index(weak[0])]):.2f} of full scale (a colour pattern with one channel? "
                       "patterns are read as gray)")
        return out

    # --- frames -------------------------------------------------------------------------------
    def __len__(self) -> int:
        return len(self.names)

    def frame_indices(self, frames) -> list[int]:
        """Resolve a frame selection to indices.

        `frames`: an int, a name, or a list of them, or a comma-separated string of tokens; a token is a
        frame name, an index, a slice `a:b`, a role selector (`gray:col:bit=0-6`, `phase:row`, `white`; see
        `slwarp.scans.roles`) or a glob of names (`gc_col_b*`), tried in that order. Order is kept (a role
        selector or glob adds its frames in scan order), duplicates dropped.
        """
        if isinstance(frames, (int, np.integer)):
            tokens = [int(frames)]
        elif isinstance(frames, str):
            tokens = [t.strip() for t in frames.split(",") if t.strip()]
        else:
            tokens = list(frames)
        out: list[int] = []
        n = len(self.names)
        where = self.source or "scan"
        for tok in tokens:
            hits: list[int]
            if isinstance(tok, str) and tok in self.names:  # a frame's own name first (NeSS tags may be digits)
                hits = [self.names.index(tok)]
            elif isinstance(tok, (int, np.integer)) or (isinstance(tok, str) and re.fullmatch(r"-?\d+", tok)):
                i = int(tok)
                if not -n <= i < n:
                    raise ScanError(f"{where}: frame index {i} out of range (0..{n - 1})")
                hits = [i % n]
            elif isinstance(tok, str) and re.fullmatch(r"-?\d*:-?\d*", tok):
                a, b = tok.split(":")
                hits = list(range(n))[slice(int(a) if a else None, int(b) if b else None)]
            else:
                try:
                    sel = parse_selector(str(tok))
                except RoleError as e:
                    raise ScanError(f"{where}: {e}") from None
                if sel is not None:
                    hits = [i for i, r in enumerate(self.roles) if sel.matches(r)]
                    if not hits:
                        raise ScanError(f"{where}: no frame has a role matching {tok!r}; the frames by role: "
                                        + "; ".join(lab for lab, _ in role_groups(self.names, self.roles)))
                else:
                    hits = [i for i, nm in enumerate(self.names) if fnmatch.fnmatchcase(nm, str(tok))]
                    if not hits:
                        raise ScanError(f"{where}: no frame matches {tok!r}; frames are: {', '.join(self.names)}")
            out.extend(h for h in hits if h not in out)
        if not out:
            raise ScanError(f"{where}: the frame selection {frames!r} is empty")
        return out

    def select(self, frames) -> "Scan":
        """A scan with a subset of the frames (see `frame_indices`), sharing calibration and ground truth."""
        idx = self.frame_indices(frames)
        return replace(self, images=self.images[idx], patterns=self.patterns[idx], names=[self.names[i] for i in idx])

    def has(self, *names: str) -> bool:
        return all(n in self.names for n in names)

    def frames_with(self, kind: str, **fields) -> list[int]:
        """Indices of the frames whose role is of `kind` with these field values (e.g. axis='col', bit=0,
        inverse=False), in scan order."""
        return [i for i, r in enumerate(self.roles)
                if r is not None and r.kind == kind and all(getattr(r, k) == v for k, v in fields.items())]

    def frame_with(self, kind: str, **fields) -> int | None:
        """Index of the one frame with this role (see `frames_with`), or None. ValueError when several match."""
        hits = self.frames_with(kind, **fields)
        if len(hits) > 1:
            raise ValueError(f"{len(hits)} frames match role {kind} {fields}: {[self.names[i] for i in hits]}")
        return hits[0] if hits else None

    def frame(self, name: str) -> tuple[np.ndarray, np.ndarray]:
        """(image, pattern) of the frame called `name`."""
        i = self.names.index(name)
        return self.images[i], self.patterns[i]

    def image(self, name: str) -> np.ndarray:
        return self.images[self.names.index(name)]

    # --- summary ------------------------------------------------------------------------------
    def summary(self, each_frame: bool = False) -> str:
        """Rig, depth range, frames grouped by role (a selector per group: see `slwarp.scans.roles`), ground
        truth; with `each_frame`, one line per frame with its role."""
        lines = [
            f"scan: {self.source or '(in memory)'}",
            f"  camera:    {self.camera.describe()}",
            f"  projector: {self.projector.describe()}",
            f"  depth range: {self.depth_range[0]:.1f} .. {self.depth_range[1]:.1f} mm" if self.depth_range else "  depth range: not given",
            f"  frames: {len(self.names)}, by role (selectors for --frames):",
        ]
        groups = role_groups(self.names, self.roles)
        width = max(len(label) for label, _ in groups)
        for label, members in groups:
            shown = ", ".join(members) if len(members) <= 6 else f"{', '.join(members[:3])}, ... {members[-1]}"
            count = f"{len(members)} frame{'s' if len(members) > 1 else ''}"
            lines.append(f"    {label:{width}s}  {count}: {shown}")
        if self.gt_depth is not None:
            valid = np.isfinite(self.gt_depth)
            if valid.any():
                lo, hi = np.nanmin(self.gt_depth), np.nanmax(self.gt_depth)
                lines.append(f"  ground truth depth: yes ({valid.mean() * 100:.1f}% valid, {lo:.1f} .. {hi:.1f} mm)")
            else:
                lines.append("  ground truth depth: yes (no valid pixel)")
        else:
            lines.append("  ground truth depth: no")
        lines.append(f"  mask: {'yes (%.1f%% set)' % (self.mask.mean() * 100) if self.mask is not None else 'no'}")
        if each_frame:
            lines.append("  frame roles:")
            width = max(len(n) for n in self.names)
            for i, (n, r) in enumerate(zip(self.names, self.roles)):
                lines.append(f"    {i:3d}  {n:{width}s}  {r.label() if r is not None else '(no role)'}")
        return "\n".join(lines)

    # --- saving -------------------------------------------------------------------------------
    def save(self, folder: str | os.PathLike, bits: int = 8) -> Path:
        """Write the native layout: scan.yaml, images/, patterns/, gt_depth.npy + gt_depth.png, mask.png.

        bits: bit depth of the camera images (8 or 16). Patterns are 8-bit when binary, else 16-bit.
        """
        import yaml

        folder = Path(folder)
        (folder / "images").mkdir(parents=True, exist_ok=True)
        (folder / "patterns").mkdir(parents=True, exist_ok=True)
        frames = []
        for i, name in enumerate(self.names):
            img_rel = f"images/{i:03d}_{name}.png"
            pat_rel = f"patterns/{name}.png"
            write_image(folder / img_rel, self.images[i], bits)
            pat = self.patterns[i]
            binary = bool(np.all((pat == 0) | (pat == 1)))
            write_image(folder / pat_rel, pat, 8 if binary else 16)
            entry = {"name": name, "image": img_rel, "pattern": pat_rel}
            if self.roles[i] is not None:
                entry["role"] = self.roles[i].to_yaml()
            frames.append(entry)
        doc = {
            "units": "mm",
            "camera": self.camera.to_dict(),
            "projector": self.projector.to_dict(),
            "extrinsics": self.projector.extrinsics_dict(),
        }
        if self.depth_range is not None:
            doc["depth_range"] = [float(self.depth_range[0]), float(self.depth_range[1])]
        doc["frames"] = frames
        if self.gt_depth is not None:
            np.save(folder / "gt_depth.npy", self.gt_depth.astype(np.float32))
            write_depth_png(folder / "gt_depth.png", self.gt_depth)
            doc["gt_depth"] = "gt_depth.npy"
        if self.mask is not None:
            write_image(folder / "mask.png", self.mask.astype(np.float32), 8)
            doc["mask"] = "mask.png"
        if self.meta:
            doc["meta"] = self.meta
        with open(folder / SCAN_FILE, "w") as f:
            yaml.safe_dump(doc, f, sort_keys=False, default_flow_style=None, width=120)
        return folder


# ----------------------------------------------------------------------------------------------
# loading


def load_scan(path: str | os.PathLike, frames=None, capture: int | str | None = None,
              outside_paths: bool | None = None) -> Scan:
    """Load a scan, detecting the layout: native (scan.yaml), NeSS (config.ini) or procam
    (calibration_result.xml). `frames` selects a subset (see `Scan.frame_indices`); `capture` picks
    capture_N in the procam layout (default: the first one). outside_paths: whether files outside the scan folder
    (links followed) may be read: None: only when scan.yaml says `allow_outside_paths: true`; True: yes; False:
    never, whatever scan.yaml says (a scan from others). ScanError naming the entry otherwise."""
    path = Path(path)
    if not path.exists():
        raise ScanError(f"scan not found: {path}")
    if path.is_file():
        if path.name == SCAN_FILE:
            path = path.parent
        else:
            raise ScanError(f"a scan is a folder (with {SCAN_FILE}, config.ini or calibration_result.xml), got a file: {path}")
    if (path / SCAN_FILE).is_file():
        scan = _load_native(path, outside_paths)
    elif (path / "config.ini").is_file():
        scan = _load_ness(path, _Confined(path, path, bool(outside_paths)))
    elif (path / "calibration_result.xml").is_file():
        scan = _load_procam(path, capture, bool(outside_paths))
    elif path.name.startswith("capture_") and (path.parent / "calibration_result.xml").is_file():
        scan = _load_procam(path.parent, path.name, bool(outside_paths))
    else:
        raise ScanError(
            f"{path}: no scan found: missing {SCAN_FILE} (native layout), config.ini (NeSS layout) or "
            "calibration_result.xml (procam layout)"
        )
    return scan.select(frames) if frames is not None else scan


def inside_folder(path: str | os.PathLike, folder: str | os.PathLike) -> bool:
    """Whether `path` lies inside `folder` once every link in both is followed (a path that does not exist yet is
    judged by the links it passes through)."""
    real, root = os.path.realpath(path), os.path.realpath(folder)
    try:
        return os.path.commonpath([real, root]) == root
    except ValueError:  # on different drives (Windows)
        return False


class _Confined:
    """The files of one scan folder: `path(entry, relative)` gives folder / relative, or ScanError naming `source`
    (the file whose entry names it), the entry and where it leads when that lies outside the folder (links
    followed) and `allow` is off. Why: a scanning station reads folders that others wrote; a scan.yaml naming
    /home/... or ../.. would make it read (and report on) files that are not the scan's."""

    def __init__(self, folder: Path, source: Path, allow: bool, hint: str | None = None):
        self.folder, self.source, self.allow = folder, source, allow
        self.hint = hint or "allow it with --allow-outside-paths (Python: load_scan(..., outside_paths=True))"

    def path(self, entry: str, relative) -> Path:
        if not isinstance(relative, str) or not relative.strip():
            raise ScanError(f"{self.source}: {entry} must be a file path relative to the scan folder, got {relative!r}")
        p = self.folder / relative
        if not self.allow and not inside_folder(p, self.folder):
            named = entry if entry == relative else f"{entry} {relative!r}"  # a fixed name once (config.ini)
            raise ScanError(f"{self.source}: {named} leads outside the scan folder (to "
                            f"{os.path.realpath(p)}); a scan's files are read from inside its folder: copy it in, or "
                            f"{self.hint}")
        return p

    def files(self, entry: str, paths) -> list[Path]:
        """`paths` found in the folder (e.g. by a glob: a link there may lead out), each checked as `path` does."""
        out = []
        for p in paths:
            try:
                relative = p.relative_to(self.folder).as_posix()
            except ValueError:  # found in a folder already allowed outside (a procam capture given by path)
                relative = str(p)
            out.append(self.path(entry, relative))
        return out


def _load_stack(files: list[tuple[Path, str]], shape: tuple[int, int], kind: str, size_name: str) -> np.ndarray:
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


def _wrap_calibration(where: Path, fn):
    try:
        return fn()
    except CalibrationError as e:
        raise ScanError(f"{where}: {e}") from None


def _load_native(folder: Path, outside_paths: bool | None = None) -> Scan:
    import yaml

    f = folder / SCAN_FILE
    if not outside_paths and not inside_folder(f, folder):  # its own flag cannot vouch for it
        raise ScanError(f"{f}: a link to {os.path.realpath(f)}, outside the scan folder; copy it in, or allow it with "
                        "--allow-outside-paths (Python: load_scan(..., outside_paths=True))")
    try:
        doc = yaml.safe_load(f.read_text())
    except yaml.YAMLError as e:
        raise ScanError(f"{f}: not valid YAML ({e})") from None
    if not isinstance(doc, dict):
        raise ScanError(f"{f}: expected a mapping with camera, projector, extrinsics and frames")
    for key in ("camera", "projector", "extrinsics", "frames"):
        if key not in doc:
            raise ScanError(f"{f}: missing key {key!r}")
    flag = doc.get(OUTSIDE_FLAG, False)
    if not isinstance(flag, bool):
        raise ScanError(f"{f}: {OUTSIDE_FLAG} must be true or false, got {flag!r}")
    if outside_paths is None:
        files = _Confined(folder, f, flag, hint=f"allow it with {OUTSIDE_FLAG}: true in {SCAN_FILE} or "
                          "--allow-outside-paths (Python: load_scan(..., outside_paths=True))")
    elif outside_paths:
        files = _Confined(folder, f, True)
    else:
        files = _Confined(folder, f, False, hint="this scan is read with files outside refused "
                          f"(--no-allow-outside-paths; Python: outside_paths=False), whatever its {OUTSIDE_FLAG} says")
    units = doc.get("units", "mm")
    if units != "mm":
        raise ScanError(f"{f}: units must be 'mm', got {units!r}")
    camera = _wrap_calibration(f, lambda: Camera.from_dict(doc["camera"], "camera"))
    projector = _wrap_calibration(f, lambda: Projector.from_dicts(doc["projector"], doc["extrinsics"]))
    frames = doc["frames"]
    if not isinstance(frames, list) or not frames:
        raise ScanError(f"{f}: the frame list is empty")
    img_files, pat_files, names, declared = [], [], [], {}
    for i, fr in enumerate(frames):
        if not isinstance(fr, dict) or "image" not in fr or "pattern" not in fr:
            raise ScanError(f"{f}: frame {i} needs 'image' and 'pattern' entries, got {fr!r}")
        img_files.append((files.path(f"frames[{i}].image", fr["image"]), f"image of frame {i}"))
        pat_files.append((files.path(f"frames[{i}].pattern", fr["pattern"]), f"pattern of frame {i}"))
        names.append(str(fr.get("name", f"frame{i}")))
        if "role" in fr:
            if fr["role"] is None:
                raise ScanError(f"{f}: frame {i} ({names[-1]!r}) has an empty role (give a role or leave the key out)")
            declared[names[-1]] = fr["role"]
    images = _load_stack(img_files, (camera.height, camera.width), "image", "camera")
    patterns = _load_stack(pat_files, (projector.height, projector.width), "pattern", "projector")
    gt_file = files.path("gt_depth", doc["gt_depth"]) if doc.get("gt_depth") else None
    mask_file = files.path("mask", doc["mask"]) if doc.get("mask") else None
    gt = read_depth(gt_file, "gt_depth") if gt_file is not None else None
    if gt is not None and gt.shape != (camera.height, camera.width):
        raise ScanError(f"gt_depth size {gt.shape[1]}x{gt.shape[0]} != camera size {camera.width}x{camera.height}: {gt_file}")
    mask = _read_mask(mask_file) if mask_file is not None else None
    if mask is not None and mask.shape != (camera.height, camera.width):
        raise ScanError(f"mask size {mask.shape[1]}x{mask.shape[0]} != camera size: {mask_file}")
    dr = doc.get("depth_range")
    if dr is not None and (not isinstance(dr, (list, tuple)) or len(dr) != 2):
        raise ScanError(f"{f}: depth_range must be [near, far] in mm, got {dr!r}")
    try:
        return Scan(camera, projector, images, patterns, names, depth_range=tuple(dr) if dr else None,
                    gt_depth=gt, mask=mask, source=str(folder), meta=doc.get("meta") or {}, declared_roles=declared)
    except ScanError as e:
        raise ScanError(f"{f}: {e}") from None


# --- NeSS layout (the authors' data): config.ini [RawCalib] + img/ + pat/ + gt/ -------------------


def _floats(cfg_file: Path, section, key: str, count: int | None) -> np.ndarray:
    if key not in section:
        raise ScanError(f"{cfg_file}: [{section.name}] is missing {key!r}")
    try:
        vals = np.array([float(x) for x in re.split(r"[,\s]+", section[key].strip()) if x], np.float64)
    except ValueError:
        raise ScanError(f"{cfg_file}: [{section.name}] {key} is not a list of numbers: {section[key]!r}") from None
    if count is not None and vals.size != count:
        raise ScanError(f"{cfg_file}: [{section.name}] {key} needs {count} numbers, got {vals.size}")
    return vals


def _natural_key(s: str):
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", s)]


# The authors' frame tags (pat/pat_<tag>.png, img/img_<tag>.png; grammar from their experiment scripts):
#   arr{size}r{i}[inv]      i-th random pattern of size-px squares (and its inverse)
#   gc{k}[inv]              Gray code bit k over the projector columns, 0 = most significant (and its inverse)
#   pm{P}n{N}i{k}           step k of an N-step phase shift over the columns with period P px
#   uni{L}                  uniform frame at level L of 255 (uni255: white, uni0: black)
_NESS_TAGS = [
    (re.compile(r"arr(\d+(?:\.\d+)?)r(\d+)(inv)?"),
     lambda m: FrameRole("random", size=float(m[1]), index=int(m[2]), inverse=bool(m[3]))),
    (re.compile(r"gc(\d+)(inv)?"), lambda m: FrameRole("gray", axis="col", bit=int(m[1]), inverse=bool(m[2]))),
    (re.compile(r"pm(\d+(?:\.\d+)?)n(\d+)i(\d+)"),
     lambda m: FrameRole("phase", axis="col", period=float(m[1]), steps=int(m[2]), step=int(m[3]))),
    (re.compile(r"uni(\d+)"),
     lambda m: FrameRole("white") if int(m[1]) == 255 else FrameRole("black") if int(m[1]) == 0
     else FrameRole("uniform", level=int(m[1]) / 255.0)),
]


def ness_role(tag: str) -> FrameRole | None:
    """The role of a NeSS frame tag (see the grammar above), or None for a tag outside it (kept, no role).
    A tag that fits the grammar with impossible values (pm40n3i5) is a ScanError naming it."""
    for pattern, make in _NESS_TAGS:
        m = pattern.fullmatch(tag)
        if m:
            try:
                return parse_role(make(m))
            except RoleError as e:
                raise ScanError(f"NeSS frame tag {tag!r}: {e}") from None
    return None


def ness_order_key(tag: str):
    """Sort key giving the authors' frame order (as their experiment scripts list the frames): random patterns
    coarse to fine (arr20r0, arr20r1, ..., arr10r0, ..., arr5r0), each inverse right after its pattern; then
    the Gray code bits, most significant first, each inverse after its bit; the phase-shift sets, the longest
    period first, steps in order; uniform frames, brightest first; other tags last, in natural order."""
    r = ness_role(tag)
    if r is None:
        return (5, _natural_key(tag))
    if r.kind == "random":
        return (0, -r.size, r.index, r.inverse)
    if r.kind == "gray":
        return (1, r.bit, r.inverse)
    if r.kind == "phase":
        return (2, -r.period, r.steps, r.step)
    level = {"white": 1.0, "black": 0.0}.get(r.kind, r.level)
    return (3, -level)


def _load_ness(folder: Path, files: _Confined) -> Scan:
    cfg_file = files.path("config.ini", "config.ini")
    # no %-interpolation: the values are numbers, and a stray '%' then reads as a bad number (a ScanError) instead of
    # configparser's InterpolationSyntaxError when the value is read
    cfg = configparser.ConfigParser(interpolation=None)
    try:
        cfg.read(cfg_file, encoding="utf-8")
    except configparser.Error as e:
        raise ScanError(f"{cfg_file}: not a valid INI file ({e})") from None
    sec_name = next((s for s in ("RawCalib", "Calibration") if s in cfg), None)
    if sec_name is None:
        raise ScanError(f"{cfg_file}: missing section [RawCalib]")
    sec = cfg[sec_name]
    img_w, img_h = _floats(cfg_file, sec, "img_size", 2).astype(int)
    pat_w, pat_h = _floats(cfg_file, sec, "pat_size", 2).astype(int)
    fx, fy, cx, cy = _floats(cfg_file, sec, "img_intrin", 4)
    pfx, pfy, pcx, pcy = _floats(cfg_file, sec, "pat_intrin", 4)
    R = _floats(cfg_file, sec, "ext_rot", 9).reshape(3, 3)
    T = _floats(cfg_file, sec, "ext_tran", 3)
    zr = _floats(cfg_file, sec, "z_range", 2) if "z_range" in sec else None
    camera = _wrap_calibration(cfg_file, lambda: Camera(img_w, img_h, [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]))
    projector = _wrap_calibration(
        cfg_file, lambda: Projector(pat_w, pat_h, [[pfx, 0, pcx], [0, pfy, pcy], [0, 0, 1]], R=check_rotation(R, "ext_rot"), T=T)
    )
    pats = {p.stem[4:]: p for p in files.files("pattern", sorted((folder / "pat").glob("pat_*.png")))}
    imgs = {p.stem[4:]: p for p in files.files("image", sorted((folder / "img").glob("img_*.png")))}
    if not pats:
        raise ScanError(f"{folder / 'pat'}: no pattern images pat_<tag>.png")
    missing = sorted(set(pats) - set(imgs), key=_natural_key)
    if missing:
        raise ScanError(f"{folder / 'img'}: image count != pattern count: no img_<tag>.png for tags {missing}")
    tags = sorted(pats, key=ness_order_key)
    images = _load_stack([(imgs[t], f"image img_{t}") for t in tags], (img_h, img_w), "image", "camera")
    patterns = _load_stack([(pats[t], f"pattern pat_{t}") for t in tags], (pat_h, pat_w), "pattern", "projector")
    gt_file = files.path("ground truth", "gt/depth.png") if (folder / "gt" / "depth.png").is_file() else None
    mask_file = files.path("mask", "gt/mask_occ.png") if (folder / "gt" / "mask_occ.png").is_file() else None
    gt = read_depth(gt_file, "gt/depth.png") if gt_file is not None else None
    mask = _read_mask(mask_file) if mask_file is not None else None
    try:
        return Scan(camera, projector, images, patterns, tags, depth_range=tuple(zr) if zr is not None else None,
                    gt_depth=gt, mask=mask, source=str(folder),
                    declared_roles={t: r for t in tags if (r := ness_role(t)) is not None})
    except ScanError as e:
        raise ScanError(f"{folder}: {e}") from None


# --- procam-calibration layout (OpenCV structured_light.GrayCodePattern captures) ------------------


def _procam_names(width: int, height: int) -> list[str]:
    """Frame order of OpenCV's GrayCodePattern: column bits (MSB first, each + inverse), row bits, white, black."""
    ncol, nrow = math.ceil(math.log2(width)), math.ceil(math.log2(height))
    names = []
    for axis, n in (("col", ncol), ("row", nrow)):
        for k in range(n):
            names += [f"gc_{axis}_b{k}", f"gc_{axis}_b{k}_inv"]
    return names + ["white", "black"]


def _load_procam(folder: Path, capture, outside_paths: bool = False) -> Scan:
    import cv2

    files = _Confined(folder, folder, outside_paths)
    xml = files.path("calibration_result.xml", "calibration_result.xml")
    try:
        return _load_procam_with(folder, capture, xml, _read_procam_calibration(xml), files)
    except (cv2.error, SystemError) as e:
        # OpenCV's parser reports a truncated file or a malformed matrix as cv2.error or (from its Python
        # binding) SystemError: the file is at fault, not the program
        detail = ("OpenCV cannot parse it" if isinstance(e, SystemError) or not str(e).strip()
                  else str(e).strip().splitlines()[-1])
        raise ScanError(f"{xml}: truncated or malformed calibration XML ({detail})") from None


def _read_procam_calibration(xml: Path) -> dict:
    """{key: float64 matrix} of a procam calibration_result.xml (cv2.FileStorage); ScanError when missing."""
    import cv2

    fs = cv2.FileStorage(str(xml), cv2.FILE_STORAGE_READ)
    if not fs.isOpened():
        raise ScanError(f"{xml}: not a readable OpenCV FileStorage file")

    def mat(*keys):
        for k in keys:
            node = fs.getNode(k)
            if not node.empty():
                m = node.mat()
                if m is None:
                    raise ScanError(f"{xml}: {k} is not a matrix")
                return np.asarray(m, np.float64)
        raise ScanError(f"{xml}: missing {' or '.join(keys)}")

    calib = {"cam_K": mat("cam_int"), "cam_d": mat("cam_dist"), "prj_K": mat("proj_int"), "prj_d": mat("proj_dist"),
             "R": mat("rotation", "roration"), "T": mat("translation")}
    fs.release()
    return calib


def _load_procam_with(folder: Path, capture, xml: Path, calib: dict, files: _Confined) -> Scan:
    cam_K, cam_d, prj_K, prj_d, R, T = (calib[k] for k in ("cam_K", "cam_d", "prj_K", "prj_d", "R", "T"))
    caps = sorted((p for p in folder.glob("capture_*") if p.is_dir()), key=lambda p: _natural_key(p.name))
    if not caps:
        raise ScanError(f"{folder}: no capture_N folder")
    if capture is None:
        cap = caps[0]
    else:
        cap = files.path("capture", capture if isinstance(capture, str) else f"capture_{capture}")
        if not cap.is_dir():
            raise ScanError(f"{folder}: capture folder {cap.name} not found (have {[c.name for c in caps]})")
    pat_files = files.files("pattern", sorted((folder / "graycode_pattern").glob("pattern_*.png"),
                                              key=lambda p: _natural_key(p.name)))
    img_files = files.files("image", sorted(cap.glob("graycode_*.png"), key=lambda p: _natural_key(p.name)))
    if not pat_files:
        raise ScanError(f"{folder / 'graycode_pattern'}: no pattern_NN.png files")
    if len(img_files) != len(pat_files):
        raise ScanError(f"{cap}: image count ({len(img_files)}) != pattern count ({len(pat_files)})")
    first = read_image(img_files[0], "image")
    first_pat = read_image(pat_files[0], "pattern")
    camera = _wrap_calibration(xml, lambda: Camera(first.shape[1], first.shape[0], cam_K, cam_d))
    projector = _wrap_calibration(
        xml, lambda: Projector(first_pat.shape[1], first_pat.shape[0], prj_K, prj_d, R=check_rotation(R, "rotation"), T=T.ravel())
    )
    names = _procam_names(projector.width, projector.height)
    if len(names) != len(pat_files):
        names = [f"frame{i:02d}" for i in range(len(pat_files))]  # not OpenCV's Gray code order: keep generic names
    images = _load_stack([(f, "image") for f in img_files], (camera.height, camera.width), "image", "camera")
    patterns = _load_stack([(f, "pattern") for f in pat_files], (projector.height, projector.width), "pattern", "projector")
    return Scan(camera, projector, images, patterns, names, source=str(cap))
