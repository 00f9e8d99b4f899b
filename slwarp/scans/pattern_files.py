"""Pattern-set files: a projector pattern set (e.g. an optimised design, slwarp.design) on disk, ready to project.

A pattern-set folder holds one 8-bit grey PNG per frame (`{name}.png`, projector resolution) and `patterns.yaml`:

    format: slwarp-pattern-set
    version: 1
    width: 1280                   # projector px
    height: 800
    frames:
    - {name: design4_0, pattern: design4_0.png, role: {kind: designed, index: 0, count: 4}}
    - ...
    meta: {...}                   # free-form provenance: rig, depth range, objective, ...

`slwarp simulate --patterns PATH` projects it, `slwarp reconstruct SCAN --patterns PATH` gives a scan's frames of the
same names these patterns (PATH: the yaml file or its folder). Roles follow scan.yaml's rules (slwarp.scans.roles):
declared ones must agree with slwarp-style names. Bad files raise ScanError naming the file and the problem.
"""
from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np

from .confinement import ConfinedFiles
from .errors import ScanError
from .images import read_image, write_image
from .patterns import PatternSet
from .roles import RoleError, parse_role, resolve_roles

__all__ = ["PATTERN_SET_FILE", "FORMAT", "VERSION", "write_pattern_set", "read_pattern_set", "read_pattern_set_meta",
           "is_pattern_set_path"]

PATTERN_SET_FILE = "patterns.yaml"
FORMAT = "slwarp-pattern-set"
VERSION = 1
_FILE_NAME = re.compile(r"[A-Za-z0-9_+-][A-Za-z0-9_.+-]*")  # a frame name that is a plain file name everywhere


def is_pattern_set_path(spec: str | os.PathLike) -> bool:
    """Whether `spec` names a pattern-set file: a path ending in .yaml / .yml (present or not: reading it then says
    what is wrong), or a folder holding patterns.yaml."""
    p = Path(spec)
    return p.suffix.lower() in (".yaml", ".yml") or (p.is_dir() and (p / PATTERN_SET_FILE).is_file())


def write_pattern_set(folder: str | os.PathLike, pset: PatternSet, meta: dict | None = None) -> Path:
    """Write `pset` into `folder` (created): one 8-bit grey PNG per frame, `{name}.png`, then patterns.yaml (last,
    written whole and renamed into place: a folder with patterns.yaml holds every PNG it names). Returns the path
    of patterns.yaml.

    Values [0, 1] are quantised to 0..255 (round to nearest): a projector shows 8 bits, so what is written is what
    it projects, and what `read_pattern_set` returns (k / 255). meta: free-form provenance (rig, depth range,
    objective, ...): numbers, strings, booleans, lists and mappings of them (numpy scalars and arrays, tuples and
    paths are written as plain numbers, lists and strings). ValueError for a frame name that is no plain file
    name, values that are not finite or outside [0, 1], or meta yaml cannot hold."""
    import yaml

    folder = Path(folder)
    bad = [n for n in pset.names if not _FILE_NAME.fullmatch(n)]
    if bad:
        raise ValueError(f"frame names {bad} are not plain file names (letters, digits, _ . + -)")
    pats = pset.patterns
    if not np.all(np.isfinite(pats)):
        raise ValueError(f"pattern values must be finite and in [0, 1]; frames {_nonfinite(pset)} hold NaN or inf")
    if pats.min() < -1e-6 or pats.max() > 1 + 1e-6:  # a design's optimiser keeps them in range: a bug upstream
        raise ValueError(f"pattern values must be finite and in [0, 1], got {pats.min():g} .. {pats.max():g}")
    roles = pset.frame_roles()
    meta = _plain(dict(meta or {}), "meta")  # before any file is written
    folder.mkdir(parents=True, exist_ok=True)
    frames = []
    for name, pat, role in zip(pset.names, pats, roles):
        write_image(folder / f"{name}.png", pat, 8)
        entry = {"name": name, "pattern": f"{name}.png"}
        if role is not None:
            entry["role"] = role.to_yaml()
        frames.append(entry)
    doc = {"format": FORMAT, "version": VERSION, "width": pset.width, "height": pset.height, "frames": frames,
           "meta": meta}
    target = folder / PATTERN_SET_FILE
    tmp = folder / f".{PATTERN_SET_FILE}.tmp"
    with open(tmp, "w") as f:
        yaml.safe_dump(doc, f, sort_keys=False, default_flow_style=None, width=120)
    os.replace(tmp, target)
    return target


def _plain(value, where: str):
    """`value` as plain yaml types (numpy scalars -> numbers, arrays and tuples -> lists, paths -> strings);
    ValueError naming the entry `where` for anything else."""
    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, os.PathLike):
        return os.fspath(value)
    if isinstance(value, np.ndarray):
        return _plain(value.tolist(), where)
    if isinstance(value, (list, tuple)):
        return [_plain(v, f"{where}[{i}]") for i, v in enumerate(value)]
    if isinstance(value, dict):
        return {str(k): _plain(v, f"{where}.{k}") for k, v in value.items()}
    raise ValueError(f"{where}: a {type(value).__name__} cannot be written to patterns.yaml (use numbers, strings, "
                     "lists and mappings)")


def _nonfinite(pset: PatternSet) -> list[str]:
    return [n for n, p in zip(pset.names, pset.patterns) if not np.all(np.isfinite(p))]


def _yaml_path(path: str | os.PathLike) -> Path:
    """patterns.yaml of `path` (the file itself, or a folder holding it); ScanError when there is none."""
    p = Path(path)
    if p.is_dir():
        if not (p / PATTERN_SET_FILE).is_file():
            raise ScanError(f"{p}: no {PATTERN_SET_FILE} in this folder (a pattern set is a folder with "
                            f"{PATTERN_SET_FILE} and one PNG per frame)")
        return p / PATTERN_SET_FILE
    if not p.is_file():
        raise ScanError(f"pattern set not found: {p}")
    return p


def _load_doc(f: Path) -> dict:
    """The checked top level of a pattern-set file: a mapping with the format tag and version."""
    import yaml

    try:
        doc = yaml.safe_load(f.read_text())
    except yaml.YAMLError as e:
        raise ScanError(f"{f}: not valid YAML ({' '.join(str(e).split())})") from None
    except UnicodeDecodeError:
        raise ScanError(f"{f}: not a text file (a pattern set is a YAML file)") from None
    if not isinstance(doc, dict):
        raise ScanError(f"{f}: not a pattern set (expected a mapping with format: {FORMAT})")
    if doc.get("format") != FORMAT:
        raise ScanError(f"{f}: not a pattern set: format is {doc.get('format')!r}, expected {FORMAT!r}")
    if doc.get("version") != VERSION:
        raise ScanError(f"{f}: pattern-set version {doc.get('version')!r} is not one this slwarp reads ({VERSION})")
    return doc


def read_pattern_set_meta(path: str | os.PathLike) -> dict:
    """The `meta` mapping of a pattern-set file (path: patterns.yaml or its folder); {} when it has none."""
    f = _yaml_path(path)
    meta = _load_doc(f).get("meta") or {}
    if not isinstance(meta, dict):
        raise ScanError(f"{f}: meta must be a mapping, got {meta!r}")
    return meta


def read_pattern_set(path: str | os.PathLike) -> PatternSet:
    """The PatternSet of a pattern-set file (path: patterns.yaml, another .yaml in the same format, or a folder
    holding patterns.yaml): patterns [K, height, width] float32 in [0, 1], names, declared roles, source = the
    yaml's path. Every PNG is read from the file's folder (links followed) and must be width x height. ScanError
    naming the file and the problem: missing or malformed yaml, wrong format tag or version, a frame PNG missing,
    unreadable or of the wrong size, duplicate names, roles that are malformed or contradict the names."""
    f = _yaml_path(path)
    doc = _load_doc(f)
    size = []
    for key in ("width", "height"):
        v = doc.get(key)
        if isinstance(v, bool) or not isinstance(v, int) or v < 1:
            raise ScanError(f"{f}: {key} must be a positive integer (projector px), got {v!r}")
        size.append(v)
    width, height = size
    frames = doc.get("frames")
    if not isinstance(frames, list) or not frames:
        raise ScanError(f"{f}: the frame list is empty (frames: [{{name, pattern, role}}, ...])")
    files = ConfinedFiles(f.parent, f, False, hint="a pattern set's PNGs are read from its folder: copy it in")
    names, pats, declared = [], [], {}
    for i, fr in enumerate(frames):
        if not isinstance(fr, dict) or not isinstance(fr.get("name"), str) or not fr["name"] or "pattern" not in fr:
            raise ScanError(f"{f}: frame {i} needs a 'name' and a 'pattern' (its PNG), got {fr!r}")
        name = fr["name"]
        if name in names:
            raise ScanError(f"{f}: frame name {name!r} appears twice (frames {names.index(name)} and {i})")
        png = files.path(f"frames[{i}].pattern", fr["pattern"])
        img = read_image(png, f"pattern of frame {name!r} of {f}")
        if img.shape != (height, width):
            raise ScanError(f"{png}: pattern of frame {name!r} is {img.shape[1]}x{img.shape[0]}, {f} says "
                            f"{width}x{height}")
        if "role" in fr:
            if fr["role"] is None:
                raise ScanError(f"{f}: frame {name!r} has an empty role (give a role or leave the key out)")
            try:
                declared[name] = parse_role(fr["role"])
            except RoleError as e:
                raise ScanError(f"{f}: frame {name!r}: {e}") from None
        names.append(name)
        pats.append(img)
    try:
        resolve_roles(names, declared)  # a role contradicting its name, two frames of one role
    except RoleError as e:
        raise ScanError(f"{f}: {e}") from None
    return PatternSet(np.stack(pats), names, declared or None, source=str(f))
