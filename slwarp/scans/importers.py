"""Importers of other scan layouts: the authors' NeSS layout (config.ini [RawCalib] + img/ + pat/ + gt/) and the
procam-calibration layout (calibration_result.xml + capture_N/ + graycode_pattern/, OpenCV's GrayCodePattern
captures). Each returns the keyword arguments of a `Scan` (slwarp.scans.scan builds it) and reads its files through
a `ConfinedFiles`, so that a link leading out of the scan folder is refused unless allowed."""
from __future__ import annotations

import configparser
import math
import re
from pathlib import Path

import numpy as np

from .confinement import ConfinedFiles
from .errors import ScanError, calibration_from
from .images import read_depth, read_image, read_image_stack, read_mask
from .roles import FrameRole, RoleError, parse_role
from .scanner import Camera, Projector, check_rotation

__all__ = ["read_ness", "ness_role", "ness_order_key", "read_procam"]


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


def read_ness(folder: Path, files: ConfinedFiles) -> dict:
    """The keyword arguments of the Scan in a NeSS folder (frames in `ness_order_key`'s order, roles from their
    tags); ScanError naming the file at fault."""
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
    camera = calibration_from(cfg_file, lambda: Camera(img_w, img_h, [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]))
    projector = calibration_from(
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
    images = read_image_stack([(imgs[t], f"image img_{t}") for t in tags], (img_h, img_w), "image", "camera")
    patterns = read_image_stack([(pats[t], f"pattern pat_{t}") for t in tags], (pat_h, pat_w), "pattern", "projector")
    gt_file = files.path("ground truth", "gt/depth.png") if (folder / "gt" / "depth.png").is_file() else None
    mask_file = files.path("mask", "gt/mask_occ.png") if (folder / "gt" / "mask_occ.png").is_file() else None
    gt = read_depth(gt_file, "gt/depth.png") if gt_file is not None else None
    mask = read_mask(mask_file) if mask_file is not None else None
    return dict(camera=camera, projector=projector, images=images, patterns=patterns, names=tags,
                depth_range=tuple(zr) if zr is not None else None, gt_depth=gt, mask=mask, source=str(folder),
                declared_roles={t: r for t in tags if (r := ness_role(t)) is not None})


# --- procam-calibration layout (OpenCV structured_light.GrayCodePattern captures) ------------------


def _procam_names(width: int, height: int) -> list[str]:
    """Frame order of OpenCV's GrayCodePattern: column bits (MSB first, each + inverse), row bits, white, black."""
    ncol, nrow = math.ceil(math.log2(width)), math.ceil(math.log2(height))
    names = []
    for axis, n in (("col", ncol), ("row", nrow)):
        for k in range(n):
            names += [f"gc_{axis}_b{k}", f"gc_{axis}_b{k}_inv"]
    return names + ["white", "black"]


def read_procam(folder: Path, capture, outside_paths: bool = False) -> dict:
    """The keyword arguments of the Scan in a procam-calibration folder: capture_N (`capture`: N or the folder's
    name; default: the first one) with the Gray code frames in OpenCV's order; ScanError naming the file at fault."""
    import cv2

    files = ConfinedFiles(folder, folder, outside_paths)
    xml = files.path("calibration_result.xml", "calibration_result.xml")
    try:
        return _read_procam_with(folder, capture, xml, _read_procam_calibration(xml), files)
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


def _read_procam_with(folder: Path, capture, xml: Path, calib: dict, files: ConfinedFiles) -> dict:
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
    camera = calibration_from(xml, lambda: Camera(first.shape[1], first.shape[0], cam_K, cam_d))
    projector = calibration_from(
        xml, lambda: Projector(first_pat.shape[1], first_pat.shape[0], prj_K, prj_d, R=check_rotation(R, "rotation"), T=T.ravel())
    )
    names = _procam_names(projector.width, projector.height)
    if len(names) != len(pat_files):
        names = [f"frame{i:02d}" for i in range(len(pat_files))]  # not OpenCV's Gray code order: keep generic names
    images = read_image_stack([(f, "image") for f in img_files], (camera.height, camera.width), "image", "camera")
    patterns = read_image_stack([(f, "pattern") for f in pat_files], (projector.height, projector.width), "pattern", "projector")
    return dict(camera=camera, projector=projector, images=images, patterns=patterns, names=names, source=str(cap))
