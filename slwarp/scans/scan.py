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

Modules: the Scan and its native layout here; `importers` (NeSS, procam), `images` (image and depth files),
`confinement` (a scan's files from inside its folder), `errors` (ScanError).
"""
from __future__ import annotations

import fnmatch
import math
import os
import re
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from ..evaluation.outputs import write_depth_png
from .confinement import ConfinedFiles, inside_folder
from .errors import ScanError, calibration_from
from .images import read_depth, read_image, read_image_stack, read_mask, write_image
from .importers import read_ness, read_procam
from .roles import RoleError, parse_selector, resolve_roles, role_groups
from .scanner import Camera, Projector

__all__ = ["Scan", "ScanError", "load_scan", "read_image", "read_depth", "inside_folder"]

SCAN_FILE = "scan.yaml"
OUTSIDE_FLAG = "allow_outside_paths"  # the scan.yaml key that lets its entries name files outside the folder


# ----------------------------------------------------------------------------------------------
# what Scan.problems calls black, saturated and weak

BLACK_LEVEL = 0.02  # full scale: a pixel below it counts as black
SATURATED_LEVEL = 0.99  # full scale: a pixel at or above it counts as saturated
WEAK_PATTERN_SPAN = 0.75  # a non-constant pattern spanning less (max - min, full scale) leaves little contrast


def _names(names: list[str], limit: int = 6) -> str:
    return ", ".join(names[:limit]) + (f", ... ({len(names)} in all)" if len(names) > limit else "")


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

    def with_patterns(self, pset) -> "Scan":
        """This scan with the patterns (and roles) of the PatternSet `pset` for its frames of the same names, e.g. a
        designed set (slwarp.scans.pattern_files.read_pattern_set) the scan's patterns folder lacks or holds an older
        version of. Every frame of `pset` must be one of the scan's, and `pset` the projector's size: else ScanError
        naming the pattern set (pset.source) and the scan. The other frames keep their patterns and roles."""
        where, src = self.source or "scan", pset.source or "the pattern set"
        if pset.patterns.shape[1:] != (self.projector.height, self.projector.width):
            raise ScanError(f"{src}: the pattern set is {pset.width}x{pset.height}, the projector of {where} is "
                            f"{self.projector.width}x{self.projector.height}")
        missing = [n for n in pset.names if n not in self.names]
        if missing:
            raise ScanError(f"{src}: frames {_names(missing)} of the pattern set are not in {where} (its frames: "
                            f"{_names(self.names, 8)})")
        patterns = self.patterns.copy()
        declared = dict(self.declared_roles or {})
        for name, pat, role in zip(pset.names, pset.patterns, pset.frame_roles()):
            patterns[self.names.index(name)] = pat
            declared.pop(name, None)  # the set's role replaces what scan.yaml declared
            if role is not None:
                declared[name] = role
        meta = {**self.meta, "pattern_set": pset.source} if pset.source else self.meta
        return replace(self, patterns=patterns, declared_roles=declared, meta=meta)

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
              outside_paths: bool | None = None, patterns=None) -> Scan:
    """Load a scan, detecting the layout: native (scan.yaml), NeSS (config.ini) or procam
    (calibration_result.xml). `frames` selects a subset (see `Scan.frame_indices`); `capture` picks
    capture_N in the procam layout (default: the first one). outside_paths: whether files outside the scan folder
    (links followed) may be read: None: only when scan.yaml says `allow_outside_paths: true`; True: yes; False:
    never, whatever scan.yaml says (a scan from others). ScanError naming the entry otherwise.
    patterns: a PatternSet or a pattern-set file (slwarp.scans.pattern_files) whose patterns replace those of the
    frames of the same names (`Scan.with_patterns`), before `frames` selects (a selection may then use the set's
    roles)."""
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
        scan = _scan_of(read_ness(path, ConfinedFiles(path, path, bool(outside_paths))), where=path)
    elif (path / "calibration_result.xml").is_file():
        scan = Scan(**read_procam(path, capture, bool(outside_paths)))
    elif path.name.startswith("capture_") and (path.parent / "calibration_result.xml").is_file():
        scan = Scan(**read_procam(path.parent, path.name, bool(outside_paths)))
    else:
        raise ScanError(
            f"{path}: no scan found: missing {SCAN_FILE} (native layout), config.ini (NeSS layout) or "
            "calibration_result.xml (procam layout)"
        )
    if patterns is not None:
        if not hasattr(patterns, "names"):  # a path
            from .pattern_files import read_pattern_set

            patterns = read_pattern_set(patterns)
        scan = scan.with_patterns(patterns)
    return scan.select(frames) if frames is not None else scan


def _scan_of(fields: dict, where: Path) -> Scan:
    """The Scan of an importer's fields; its ScanError (sizes, roles) names the scan folder `where`."""
    try:
        return Scan(**fields)
    except ScanError as e:
        raise ScanError(f"{where}: {e}") from None


def _load_native(folder: Path, outside_paths: bool | None = None) -> Scan:
    """The Scan of a folder in the native layout (scan.yaml); outside_paths as `load_scan` takes it."""
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
        files = ConfinedFiles(folder, f, flag, hint=f"allow it with {OUTSIDE_FLAG}: true in {SCAN_FILE} or "
                          "--allow-outside-paths (Python: load_scan(..., outside_paths=True))")
    elif outside_paths:
        files = ConfinedFiles(folder, f, True)
    else:
        files = ConfinedFiles(folder, f, False, hint="this scan is read with files outside refused "
                          f"(--no-allow-outside-paths; Python: outside_paths=False), whatever its {OUTSIDE_FLAG} says")
    units = doc.get("units", "mm")
    if units != "mm":
        raise ScanError(f"{f}: units must be 'mm', got {units!r}")
    camera = calibration_from(f, lambda: Camera.from_dict(doc["camera"], "camera"))
    projector = calibration_from(f, lambda: Projector.from_dicts(doc["projector"], doc["extrinsics"]))
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
    images = read_image_stack(img_files, (camera.height, camera.width), "image", "camera")
    patterns = read_image_stack(pat_files, (projector.height, projector.width), "pattern", "projector")
    gt_file = files.path("gt_depth", doc["gt_depth"]) if doc.get("gt_depth") else None
    mask_file = files.path("mask", doc["mask"]) if doc.get("mask") else None
    gt = read_depth(gt_file, "gt_depth") if gt_file is not None else None
    if gt is not None and gt.shape != (camera.height, camera.width):
        raise ScanError(f"gt_depth size {gt.shape[1]}x{gt.shape[0]} != camera size {camera.width}x{camera.height}: {gt_file}")
    mask = read_mask(mask_file) if mask_file is not None else None
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

