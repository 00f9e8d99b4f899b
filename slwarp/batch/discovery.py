"""Finding a batch's scans (`find_scans`: scan folders, folders of scans, globs), their output names
(`unique_names`) and sharing them out by cost (`scan_cost`, `largest_first`, `shard`)."""
from __future__ import annotations

import glob
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

from ..scans.scan import SCAN_FILE, ScanError

__all__ = ["SCAN_MARKERS", "ScanEntry", "Discovery", "find_scans", "is_scan_folder", "unique_names", "scan_cost",
           "largest_first", "shard"]

# The files by which `load_scan` recognises a scan folder's layout: native, NeSS, procam-calibration.
SCAN_MARKERS = (SCAN_FILE, "config.ini", "calibration_result.xml")
_GLOB_CHARS = frozenset("*?[")


@dataclass(frozen=True)
class ScanEntry:
    """One scan of a batch: `name` (its output folder's name, unique in the batch) and `source` (the folder)."""

    name: str
    source: Path


@dataclass
class Discovery:
    """What `find_scans` found: the scans (sorted by name), whether the command named one scan folder (its
    outputs then go straight into --out, as for a lone scan always), and the folders it passed over (in a
    folder of scans or among a glob's matches, holding no scan)."""

    scans: list[ScanEntry]
    single: bool
    ignored: list[Path] = field(default_factory=list)


def is_scan_folder(path: str | os.PathLike) -> bool:
    """Whether `path` is a folder `load_scan` recognises (it holds one of SCAN_MARKERS)."""
    path = Path(path)
    return path.is_dir() and any((path / m).is_file() for m in SCAN_MARKERS)


def _has_glob(spec: str) -> bool:
    return any(c in _GLOB_CHARS for c in spec)


def _scans_in(folder: Path, ignored: list[Path]) -> list[Path]:
    """The scan folders among `folder`'s immediate subfolders (sorted); the other subfolders go to `ignored`."""
    found = []
    for sub in sorted(p for p in folder.iterdir() if p.is_dir()):
        (found if is_scan_folder(sub) else ignored).append(sub)
    return found


def find_scans(specs: Sequence[str | os.PathLike]) -> Discovery:
    """The scans named by command-line words: each a scan folder, a folder of scan folders (its immediate
    subfolders that are scans) or a glob (`scans/day1_*`, `data/**/scan.yaml`; quote it so that the shell leaves
    it alone) whose matches are either. A `scan.yaml` file stands for its folder. The same folder named twice
    is one scan.

    Raises ScanError for a word that names no scan (a path that does not exist, a folder holding no scan, a
    glob matching none): a mistake in the command, reported before any work starts. A scan folder that exists
    but cannot be loaded is a scan of the batch: it fails alone when it runs.
    """
    if not specs:
        raise ScanError("no scan given")
    single = False
    paths: list[Path] = []
    ignored: list[Path] = []
    for spec in map(str, specs):
        if _has_glob(spec):
            matches = [Path(m) for m in sorted(glob.glob(spec, recursive=True))]
            matches = [m.parent if m.name == SCAN_FILE else m for m in matches]
            folders = [m for m in matches if m.is_dir()]
            added = 0
            for m in folders:
                if is_scan_folder(m):
                    paths.append(m)
                    added += 1
                    continue
                passed_over: list[Path] = []
                inside = _scans_in(m, passed_over)
                paths.extend(inside)
                added += len(inside)
                ignored.extend(passed_over if inside else [m])  # a match holding no scan is passed over whole
            if not added:
                raise ScanError(f"{spec}: no scan matches (a scan is a folder with one of {', '.join(SCAN_MARKERS)})")
            continue
        path = Path(spec)
        if path.is_file() and path.name == SCAN_FILE:
            path = path.parent
        if not path.exists():
            raise ScanError(f"scan not found: {spec}")
        if is_scan_folder(path):
            paths.append(path)
            single = len(specs) == 1
            continue
        if not path.is_dir():
            raise ScanError(f"{spec}: not a scan folder (a scan is a folder with one of {', '.join(SCAN_MARKERS)})")
        inside = _scans_in(path, ignored)
        if not inside:
            raise ScanError(f"{spec}: holds no scan (neither it nor its subfolders has one of {', '.join(SCAN_MARKERS)})")
        paths.extend(inside)
    unique: dict[Path, Path] = {}
    for p in paths:
        unique.setdefault(p.resolve(), Path(os.path.abspath(p)))
    folders = list(unique.values())
    names = unique_names(folders)
    scans = sorted((ScanEntry(n, p) for n, p in zip(names, folders)), key=lambda e: e.name)
    return Discovery(scans, single, ignored)


def unique_names(folders: Sequence[Path]) -> list[str]:
    """Output-folder names for scan folders: each folder's own name; folders that share a name take their
    parents' names in front, joined with '-', one level at a time until they differ (day1/bunny and
    day2/bunny: day1-bunny, day2-bunny); names still equal after that get -2, -3, ... in the given order."""
    parts = [tuple(p for p in Path(f).parts if p != Path(f).anchor) for f in folders]
    depth = [1] * len(folders)

    def name(i: int) -> str:
        return "-".join(parts[i][-depth[i]:]) or "scan"

    while True:
        groups: dict[str, list[int]] = {}
        for i in range(len(folders)):
            groups.setdefault(name(i), []).append(i)
        grew = False
        for members in groups.values():
            if len(members) > 1:
                for i in members:
                    if depth[i] < len(parts[i]):
                        depth[i] += 1
                        grew = True
        if not grew:
            break
    names, seen = [], {}
    for i in range(len(folders)):
        n = name(i)
        seen[n] = seen.get(n, 0) + 1
        names.append(n if seen[n] == 1 else f"{n}-{seen[n]}")
    return names


# ----------------------------------------------------------------------------------------------
# sharing the scans out


def scan_cost(folder: str | os.PathLike) -> float | None:
    """The relative cost of reconstructing a scan: camera pixels x frames, read from a native scan.yaml
    without loading images (the depth search and the extraction grow with both; training is the same for
    every scan of a config). None when it cannot be told cheaply (other layouts, an unreadable scan.yaml)."""
    import yaml

    try:
        doc = yaml.safe_load((Path(folder) / SCAN_FILE).read_text())
        cam = doc["camera"]
        return float(int(cam["width"]) * int(cam["height"]) * len(doc["frames"]))
    except Exception:  # any unreadable or malformed file: the scan itself reports it when it runs
        return None


def _known_costs(costs: Sequence[float | None]) -> list[float]:
    """Costs with the unknown ones set to the mean of the known ones (1 when none is known)."""
    known = [c for c in costs if c is not None]
    fill = sum(known) / len(known) if known else 1.0
    return [fill if c is None else float(c) for c in costs]


def largest_first(costs: Sequence[float | None]) -> list[int]:
    """Indices of the scans by decreasing cost; equal costs keep their order (unknown costs: see
    `_known_costs`)."""
    full = _known_costs(costs)
    return sorted(range(len(full)), key=lambda i: (-full[i], i))


def shard(costs: Sequence[float | None], n_workers: int) -> list[list[int]]:
    """Deterministic shares of the scans for `n_workers` workers (longest processing time first): scans by
    decreasing cost, each to the worker with the least total cost so far (the lowest-numbered one on a tie).
    Returns, per worker, the indices of its scans in the order it runs them. Equal costs deal round-robin."""
    if n_workers < 1:
        raise ValueError(f"n_workers must be >= 1, got {n_workers}")
    full = _known_costs(costs)
    shares: list[list[int]] = [[] for _ in range(n_workers)]
    load = [0.0] * n_workers
    for i in largest_first(full):
        w = min(range(n_workers), key=lambda k: (load[k], k))
        shares[w].append(i)
        load[w] += full[i]
    return shares

