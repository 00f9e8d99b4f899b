"""How long a process takes to start CUDA, alone and with others starting at the same moment on the same host.

    python -m bench.cuda_start --together 1,4 --rounds 3          # a 4-GPU host: one process, then four at once

Each process sees one GPU (CUDA_VISIBLE_DEVICES, as a batch's workers and torchrun's ranks do) and times three steps:
`import torch`; torch's CUDA start (`torch.cuda.init()` and a first allocation: cuInit and the device's primary
context); Warp's start (`wp.init()`). In the variant `early` the process first starts the driver and the context in a
thread through ctypes (slwarp.driver.start_driver) and the torch import runs beside it; in `torch` torch starts them.
Why: a batch's four workers were ready 3.9-4.2 s after the command started, their CUDA start alone 0.4-1.5 s
(bench/results/batch-throughput-cuda-h200x4-16-driver.md).
Writes <out>/<stem>.json and .md.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

# the measured process: prints one JSON line of its times
_CHILD = r"""
import json, sys, time
t0 = time.time()
if sys.argv[1] == "1":
    from slwarp.driver import start_driver
    start_driver(0)
import torch
t1 = time.time()
torch.cuda.init()
torch.empty(1, device="cuda")
t2 = time.time()
import warp as wp
wp.init()
t3 = time.time()
print(json.dumps(dict(torch_s=t1 - t0, cuda_s=t2 - t1, warp_s=t3 - t2, total_s=t3 - t0)))
"""


def gpu_ids() -> list[str]:
    """The GPUs this host shows (CUDA_VISIBLE_DEVICES's entries, else the driver's), without starting CUDA here."""
    from slwarp.batch.launch import visible_device_ids

    return visible_device_ids("cuda") or []


def one_round(together: int, early: bool, ids: list[str]) -> list[dict]:
    """`together` processes started at once, process k on GPU ids[k % len(ids)]; their times."""
    procs = []
    for k in range(together):
        env = {**os.environ, "CUDA_VISIBLE_DEVICES": ids[k % len(ids)], "PYTHONUNBUFFERED": "1"}
        procs.append(subprocess.Popen([sys.executable, "-c", _CHILD, "1" if early else "0"], env=env, cwd=REPO,
                                      stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True))
    rows = []
    for k, p in enumerate(procs):
        out, err = p.communicate(timeout=300)
        if p.returncode != 0:
            raise RuntimeError(f"process {k} failed: {err.strip()[-500:]}")
        row = json.loads(out.strip().splitlines()[-1])
        rows.append(dict(gpu=ids[k % len(ids)], **row))
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--together", default="1,4", help="comma-separated process counts started at once")
    ap.add_argument("--rounds", type=int, default=3, help="rounds per count and variant")
    ap.add_argument("--variants", default="torch,early", help="torch (torch starts CUDA), early (slwarp.driver first)")
    ap.add_argument("--out", default="bench/results")
    ap.add_argument("--stem", default="cuda-start-cuda")
    args = ap.parse_args(argv)
    ids = gpu_ids()
    if not ids:
        print("no GPU visible: nothing to measure", file=sys.stderr)
        return 1
    counts = [int(c) for c in args.together.split(",")]
    variants = args.variants.split(",")
    results = []
    for _ in range(args.rounds):  # variants interleaved, round after round: a host's drift falls on both
        for n in counts:
            for v in variants:
                rows = one_round(n, v == "early", ids)
                results.append(dict(together=n, variant=v, processes=rows))
                print(f"{n} at once, {v}: " + ", ".join(f"{r['total_s']:.2f}" for r in rows) + " s", flush=True)
    import torch

    name = torch.cuda.get_device_name(0) if torch.cuda.is_available() else "?"
    cmd = "python -m bench.cuda_start " + " ".join(argv if argv is not None else sys.argv[1:])
    doc = dict(device=f"{len(ids)} x {name}", date=time.strftime("%Y-%m-%d"), command=cmd, results=results)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / f"{args.stem}.json").write_text(json.dumps(doc, indent=1))
    lines = [f"# CUDA's start per process, {doc['device']}, {doc['date']}", "", f"`{cmd}`", "",
             "Seconds per process (min-max over the processes and rounds): `import torch`; torch's CUDA start "
             "(cuInit, the context, a first allocation); Warp's start; all three from the process's first line.", "",
             "| processes at once | variant | import torch | CUDA start | Warp start | total |", "|---:|---|---|---|---|---|"]
    for n in counts:
        for v in variants:
            rows = [r for res in results if res["together"] == n and res["variant"] == v for r in res["processes"]]
            span = {k: f"{min(r[k] for r in rows):.2f}-{max(r[k] for r in rows):.2f}"
                    for k in ("torch_s", "cuda_s", "warp_s", "total_s")}
            lines.append(f"| {n} | {v} | {span['torch_s']} | {span['cuda_s']} | {span['warp_s']} | {span['total_s']} |")
    (out / f"{args.stem}.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
