"""What a scanning station costs each scan: `slwarp watch INBOX --out OUT --until-idle` over simulated scans already
in its inbox, as fresh processes, each output line timed from the command's start. The mean time between the scans'
lines after the first is what each later scan costs a station (its files written: a line comes once they are).

    python -m bench.watch_station --preset fast --scans 8 --runs 2     # CUDA: default rig; run 1 fills the caches
    python -m bench.watch_station --smoke                              # CPU: 3 small scans, tiny settings

The scans (scenes in turn, a noise seed per round) are made once into <work>/inbox; each run writes into its own
<work>/out-K. The caches a machine keeps (Warp's kernels, Inductor's and Triton's) live in <work>/caches, empty
before the first run with --cold. Writes <out>/<stem>.json and .md.
"""
from __future__ import annotations

import argparse
import datetime
import os
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

from bench import write_study
from bench.command_wall import compile_bytecode, option_flags, process_env

REPO = Path(__file__).resolve().parents[1]
SCENES = ("bunny", "vase", "spheres", "torus")
SMOKE_SET = ["iters=3", "init_iters=2", "mc_resolution=32", "rays=64"]
# a scan's line: "NAME: SECONDS s, depth on ..." (slwarp.watch.line)
SCAN_LINE = re.compile(r"^(\S+): ([0-9.]+) s, ")


def make_inbox(inbox: Path, scans: int, rig: str, env: dict) -> list[str]:
    """Simulate `scans` scans into inbox (once: kept between calls); their folder names."""
    names = []
    for k in range(scans):
        scene, seed = SCENES[k % len(SCENES)], k // len(SCENES)
        name = f"{k:02d}-{scene}"
        names.append(name)
        folder = inbox / name
        if (folder / "scan.yaml").is_file():
            continue
        made = subprocess.run([sys.executable, "-m", "slwarp", "simulate", "--scene", scene, "--rig", rig, "--seed",
                               str(seed), "--out", str(folder)], cwd=REPO, env=env, capture_output=True, text=True)
        if made.returncode:
            raise SystemExit(f"could not simulate {folder}:\n{made.stdout[-800:]}{made.stderr[-800:]}")
    return names


def run_station(cmd: list[str], env: dict) -> dict:
    """One fresh `slwarp watch` process: its lines, each with the seconds since spawn, and what they say."""
    t0 = time.time()
    p = subprocess.Popen(cmd, cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, bufsize=1)
    lines = [[round(time.time() - t0, 3), line.rstrip("\n")] for line in p.stdout]
    rc = p.wait()
    wall = time.time() - t0
    scans = [(t, m.group(1)) for t, text in lines if (m := SCAN_LINE.match(text))]
    times = [t for t, _ in scans]
    gaps = [b - a for a, b in zip(times, times[1:])]
    return {"rc": rc, "wall_s": wall, "lines": lines, "scans_done": len(scans),
            "first_scan_s": times[0] if times else None,
            "later_scan_s": (times[-1] - times[0]) / (len(times) - 1) if len(times) > 1 else None,
            "gaps_s": gaps}


def markdown(doc: dict) -> str:
    s = doc["setup"]
    out = [f"# `slwarp watch`: {s['scans']} `{s['preset']}` scans in the inbox, {doc['device']}, {doc['date']}", "",
           f"`{doc['bench_command']}`", "",
           f"Each run: `{' '.join(doc['command'])}` as a fresh process, the scans ({s['rig']} rig, random 6, scenes "
           f"{', '.join(SCENES)} in turn, a noise seed per round) in the inbox before it starts, each output line "
           "timed "
           "from its spawn. A later scan: the mean time between the scans' lines after the first (each line comes "
           "once the scan's files are written).", "",
           "| run | caches | scans done | command s | first scan's line s | each later scan s | between lines s |",
           "|---|---|---:|---:|---:|---:|---|"]
    for k, r in enumerate(doc["runs"], 1):
        first = f"{r['first_scan_s']:.2f}" if r["first_scan_s"] is not None else "-"
        later = f"{r['later_scan_s']:.2f}" if r["later_scan_s"] is not None else "-"
        out.append(f"| {k} | {r['caches']} | {r['scans_done']} | {r['wall_s']:.1f} | {first} | {later} | "
                   + " / ".join(f"{g:.2f}" for g in r["gaps_s"]) + " |")
    out += ["", "The lines (seconds since the command started; a line's own figure is that scan's time from its start "
            "to its depth map and metrics, which overlaps the scans before and after it):", "", "```"]
    for k, r in enumerate(doc["runs"], 1):
        out.append(f"# run {k}")
        out += [f"{t:8.2f}  {text}" for t, text in r["lines"]]
    return "\n".join(out + ["```", ""])


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--preset", default=None, help="default: fast on CUDA, tiny with --smoke")
    p.add_argument("--scans", type=int, default=8)
    p.add_argument("--rig", default=None, help="default: default on CUDA, small on the CPU")
    p.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE", help="options given to the command as flags")
    p.add_argument("--runs", type=int, default=2, help="fresh station processes, one after another")
    p.add_argument("--cold", action="store_true", help="empty the caches before the first run")
    p.add_argument("--bytecode", choices=["as-is", "warm"], default="as-is",
                   help="warm: Python's bytecode compiled into <work>/pycache first, as a user's machine keeps it "
                        "(bench.command_wall)")
    p.add_argument("--work", default="/tmp/slwarp-watch-station", help="the inbox, the caches and the outputs")
    p.add_argument("--smoke", action="store_true", help="CPU, small rig, tiny preset, 3 scans, a few iterations")
    p.add_argument("--stem", default=None)
    p.add_argument("--out", default=str(REPO / "bench" / "results"))
    args = p.parse_args(argv)
    if args.runs < 1 or args.scans < 1:
        raise SystemExit("--runs and --scans must be >= 1")
    cuda = not args.smoke and bool(shutil.which("nvidia-smi")) and subprocess.run(
        ["nvidia-smi", "-L"], capture_output=True).returncode == 0
    if args.smoke:
        args.preset, args.rig, args.scans = args.preset or "tiny", args.rig or "small", min(args.scans, 3)
        args.set = SMOKE_SET + args.set
    args.preset = args.preset or "fast"
    args.rig = args.rig or ("default" if cuda else "small")
    work = Path(args.work)
    caches, env = process_env(work, args.cold, args.smoke)
    if args.bytecode == "warm":
        env["PYTHONPYCACHEPREFIX"] = str(work / "pycache")
        compile_bytecode(work / "pycache")
    inbox = work / f"inbox-{args.rig}"
    make_inbox(inbox, args.scans, args.rig, {**os.environ, "SLWARP_KERNEL_CACHE": str(work / "simulator-kernels")}
               if not args.smoke else env)
    command = ["python", "-m", "slwarp", "watch", str(inbox), "--out", "OUT", "--preset", args.preset, "--until-idle",
               *option_flags(args.set)]
    runs = []
    for k in range(args.runs):
        warm = any(f.is_file() for f in caches.rglob("*"))
        out = work / f"out-{k + 1}"
        shutil.rmtree(out, ignore_errors=True)
        row = {"caches": "filled" if warm else "empty",
               **run_station([sys.executable, *[str(out) if c == "OUT" else c for c in command[1:]]], env)}
        runs.append(row)
        print(f"run {k + 1} ({row['caches']} caches): {row['scans_done']} scans, " + (
            f"each after the first {row['later_scan_s']:.2f} s" if row["later_scan_s"] is not None else "one scan"),
            flush=True)
    device = "CPU"
    if cuda:
        device = subprocess.run(["nvidia-smi", "--query-gpu=name", "--format=csv,noheader"], capture_output=True,
                                text=True).stdout.strip().splitlines()[0]
    doc = {"device": device, "date": str(datetime.date.today()), "command": command,
           "bench_command": "python -m bench.watch_station " + " ".join(argv if argv is not None else sys.argv[1:]),
           "setup": {"preset": args.preset, "rig": args.rig, "scans": args.scans, "set": args.set, "cold": args.cold,
                     "smoke": args.smoke}, "runs": runs}
    stem = args.stem or f"watch-station-{'cuda' if cuda else 'cpu'}-{args.preset}"
    write_study(Path(args.out) / stem, doc, markdown)


if __name__ == "__main__":
    main()
