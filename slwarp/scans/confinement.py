"""A scan's files are read from inside its folder: `inside_folder` judges a path (links followed), `ConfinedFiles`
hands out a scan folder's files and refuses those that lead out of it unless allowed (docs/inputs.md)."""
from __future__ import annotations

import os
from pathlib import Path

from .errors import ScanError

__all__ = ["inside_folder", "ConfinedFiles"]


def inside_folder(path: str | os.PathLike, folder: str | os.PathLike) -> bool:
    """Whether `path` lies inside `folder` once every link in both is followed (a path that does not exist yet is
    judged by the links it passes through)."""
    real, root = os.path.realpath(path), os.path.realpath(folder)
    try:
        return os.path.commonpath([real, root]) == root
    except ValueError:  # on different drives (Windows)
        return False


class ConfinedFiles:
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
