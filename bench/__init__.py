"""slwarp's benchmarks, run from the repository root as `python -m bench.NAME` (each module's docstring has its
commands). Each writes JSON and a markdown table to bench/results/ (or --out); bench/results/README.md indexes the
current figures. The helpers below are shared by the benchmarks that write a JSON document and its table."""
from __future__ import annotations

import json
import time
from pathlib import Path

DATE = time.strftime("%Y-%m-%d")


def markdown_table(header: list[str], rows: list[list[str]]) -> list[str]:
    """Lines of a markdown table (first column left-aligned, the others right-aligned)."""
    lines = ["| " + " | ".join(header) + " |", "|---|" + "---:|" * (len(header) - 1)]
    lines += ["| " + " | ".join(str(c) for c in r) + " |" for r in rows]
    return lines


def write_study(out, doc: dict, render) -> None:
    """Write a benchmark's results: <out>.json (doc), <out>.md (render(doc)), and print the markdown."""
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".json").write_text(json.dumps(doc, indent=1, default=float))
    md = render(doc)
    out.with_suffix(".md").write_text(md)
    print(md)


def scan_on_disk(path) -> tuple[Path, str]:
    """(the scan folder `path` resolved, its name for a table: the folder's, or its parent's for a folder named
    `scan` as bench.real_captures prepares them); SystemExit naming --scan when there is no such folder."""
    scan = Path(path).resolve()
    if not scan.is_dir():
        raise SystemExit(f"--scan {path}: no such scan folder")
    return scan, scan.parent.name if scan.name == "scan" else scan.name
