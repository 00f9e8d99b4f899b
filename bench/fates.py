"""Where a neural run's errors and missing pixels come from, by pixel fate: reads the npz files that
`bench.accuracy_sweep --keep DIR` writes (signed error = depth - ground truth in mm, and each pixel's fate) and
prints one table per run.

    python -m bench.fates DIR                       # every neural run kept in DIR
    python -m bench.fates DIR --match rods          # the runs whose file name contains 'rods'
    python -m bench.fates DIR --json FATES.json     # the tables also as JSON

Per fate: pixels, pixels with a depth, pixels off by more than --gross mm, their summed and mean signed error (a
positive mean: the depth lies behind the truth, e.g. a thin part given the background's depth), and the pixels that
GC(7) of the same scan has and this run lacks (when the GC(7) file of the job is kept beside it).
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np


def fate_table(run: Path, gross_mm: float = 5.0) -> list[dict]:
    """One row per fate present in the kept run `run` (an npz with error, fate, fates)."""
    d = np.load(run, allow_pickle=True)
    err, fate, names = d["error"].astype(np.float32), d["fate"], [str(n) for n in d["fates"]]
    rig, scene, seed = run.name.split("__")[1:4]  # the job key: PRESET__RIG__SCENE__sSEED, then the method
    gc7 = run.with_name(f"classical__{rig}__{scene}__{seed}__GC7interp.npz")
    gc_has = np.isfinite(np.load(gc7)["error"]) if gc7.is_file() else None
    rows = []
    for i, name in enumerate(names):
        here = fate == i
        if not here.any():
            continue
        e = err[here & np.isfinite(err)]
        big = e[np.abs(e) > gross_mm]
        rows.append({"fate": name, "pixels": int(here.sum()), "with_depth": int(e.size), "gross": int(big.size),
                     "gross_sum_mm": float(np.abs(big).sum()), "gross_mean_mm": float(big.mean()) if big.size else None,
                     "gc7_has_we_lack": (int((here & ~np.isfinite(err) & gc_has).sum()) if gc_has is not None else None)})
    return rows


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("folder", help="a --keep folder of bench.accuracy_sweep")
    p.add_argument("--match", default="", help="only the runs whose file name contains this")
    p.add_argument("--gross", type=float, default=5.0, help="an error above this many mm counts as gross (default 5)")
    p.add_argument("--json", help="also write the tables to this JSON file ({run: rows})")
    args = p.parse_args(argv)
    runs = sorted(r for r in Path(args.folder).glob("*.npz") if not r.name.startswith("classical__")
                  and args.match in r.name)
    if not runs:
        print(f"{args.folder}: no kept neural run" + (f" matching {args.match!r}" if args.match else ""), file=sys.stderr)
        return 2
    tables = {run.stem: fate_table(run, args.gross) for run in runs}
    if args.json:
        Path(args.json).write_text(json.dumps({"folder": str(args.folder), "gross_mm": args.gross, "runs": tables},
                                              indent=1) + "\n")
    for run in runs:
        print(f"\n{run.stem}\n")
        print(f"| fate | pixels | with depth | off > {args.gross:g} mm | their sum of abs mm | their mean signed mm | "
              "GC(7) has, this lacks |")
        print("|---|---:|---:|---:|---:|---:|---:|")
        for r in tables[run.stem]:
            mean = "-" if r["gross_mean_mm"] is None else f"{r['gross_mean_mm']:+.1f}"
            lack = "-" if r["gc7_has_we_lack"] is None else str(r["gc7_has_we_lack"])
            print(f"| {r['fate']} | {r['pixels']} | {r['with_depth']} | {r['gross']} | {r['gross_sum_mm']:.0f} | "
                  f"{mean} | {lack} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
