"""Designed patterns against the paper's random 6 and Gray code: one design per rig and count, then the accuracy sweep.

1. For each rig geometry and each K in --counts: `slwarp design-patterns --rig RIG --count K` (the same code, called
   in process), written to <designs>/<rig>/design<K>/ with its design.json; the design's own time is recorded. A
   design draws random depths along the rig's rays; it never sees a scene, so the scenes measured are not the ones
   designed on (there are none).
2. `bench.accuracy_sweep --designs <designs> --neural-frames random6,design3,...`: every scene on every rig is
   simulated once with random6 + gray7 + the rig's designs; each preset trains on each set; GC(6) / GC(7)-interp
   decode the same scans.
3. A table of the targets: mean MAE of designed 4 against random 6 (the same preset) and of designed 3 against
   GC(7)-interp, per rig, with the design times.

    python -m bench.designed_patterns --presets fast                        # GPU: every rig and scene
    python -m bench.designed_patterns --small --rigs default --scenes bunny --presets cpu-hashgrid \\
        --counts 3 --iterations 100 --out /tmp/designed                     # CPU smoke run

Writes <out>/designed-patterns-<cpu|cuda>.json and .md (and the sweep's own tables beside them).
"""
from __future__ import annotations

import argparse
import datetime
import json
import os
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def design_one(rig: str, count: int, folder: str, iterations: int, device: str, seed: int, pixels: int = 4096,
               window: int = 0, window_step: int = 1, blur_spread: float | None = None) -> dict:
    """Design `count` patterns for `rig` into folder (reused when its design.json says the same options); window:
    DesignOptions.window (the depth search's window the objective scores; 0: each pixel alone); window_step: camera
    px between the window's pixels (the set's roles carry it, so the sweep's search uses the same step); blur_spread:
    NoiseModel.blur_spread (None: its default)."""
    import torch

    from slwarp.cli.design import write_design
    from slwarp.design import DesignOptions, NoiseModel, design_patterns
    from slwarp.sim.rigs import DEPTH_RANGE_MM, make_rig

    out = Path(folder)
    done = out / "design.json"
    key = {"rig": rig, "count": count, "iterations": iterations, "seed": seed, "pixels": pixels,
           **({"window": window} if window else {}), **({"window_step": window_step} if window_step > 1 else {}),
           # always named: a design made before the spread (no such key) is made again
           "blur_spread": NoiseModel().blur_spread if blur_spread is None else blur_spread}
    if done.is_file():
        prev = json.loads(done.read_text())
        if prev.get("key") == key:
            return prev
    camera, projector = make_rig(rig)
    noise = NoiseModel(blur_spread=key["blur_spread"])
    opts = DesignOptions(count=count, iterations=iterations, seed=seed, pixels=pixels, window=window,
                         window_step=window_step, noise=noise)
    if device.startswith("cuda"):
        torch.cuda.set_device(torch.device(device))
    res = design_patterns(camera, projector, DEPTH_RANGE_MM, opts, device=device, baselines=())
    write_design(out, res, f"rig {rig}", DEPTH_RANGE_MM, {"key": key, "device": device})
    return json.loads(done.read_text())


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--presets", default="fast", help="comma-separated presets for the sweep (default fast)")
    ap.add_argument("--counts", default="3,4,6", help="designed set sizes (default 3,4,6)")
    ap.add_argument("--rigs", default=None, help="comma-separated rig geometries (default: all)")
    ap.add_argument("--small", action="store_true", help="each geometry's small-resolution rig")
    ap.add_argument("--scenes", default=None, help="comma-separated scenes (default: every built-in scene)")
    ap.add_argument("--iterations", type=int, default=1500, help="descent steps per design (default 1500)")
    ap.add_argument("--pixels", type=int, default=4096, help="camera pixels per design step (default 4096)")
    ap.add_argument("--window", type=int, default=0,
                    help="design for the depth search's windows: their radius in camera px (2), 0: each pixel alone")
    ap.add_argument("--window-step", type=int, default=1,
                    help="camera px between the window's pixels (the sets' roles say it: the search uses the same)")
    ap.add_argument("--blur-spread", type=float, default=None,
                    help="the design's camera blur spread (slwarp design-patterns --blur-spread; default: its default)")
    ap.add_argument("--without-random6", action="store_true", help="no neural runs on random 6 (the designs and Gray code only)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--designs", default=None, help="folder of the designs (default <out>/designs)")
    ap.add_argument("--workers-per-gpu", type=int, default=4)
    ap.add_argument("--workers", type=int, default=None, help="processes on the CPU (default 1)")
    ap.add_argument("--max-minutes", type=float, default=None, help="passed to the sweep: stop starting runs after this "
                    "long (run the same command again to go on)")
    ap.add_argument("--out", default=str(REPO / "bench" / "results"))
    ap.add_argument("--stem", default=None, help="output file name without suffix (default designed-patterns-<cpu|cuda>)")
    args = ap.parse_args(argv)

    import multiprocessing as mp

    import torch

    from bench import accuracy_sweep
    from slwarp.sim.rigs import GEOMETRIES, rig_name

    cuda = torch.cuda.is_available()
    rigs = [rig_name(g, args.small) for g in (args.rigs.split(",") if args.rigs else GEOMETRIES)]
    counts = [int(k) for k in args.counts.split(",")]
    out = Path(args.out)
    designs = Path(args.designs) if args.designs else out / "designs"
    dev = "cuda:0" if cuda else "cpu"
    t0 = time.perf_counter()
    todo = [(r, k) for r in rigs for k in counts]
    # one process per design: each design is a few kernels per step, so several share a GPU well
    workers = min(len(todo), 6 if cuda else (args.workers or 1))
    with ProcessPoolExecutor(max_workers=workers, mp_context=mp.get_context("spawn")) as pool:
        futs = {(r, k): pool.submit(design_one, r, k, str(designs / r / f"design{k}"), args.iterations, dev, args.seed,
                                          args.pixels, args.window, args.window_step, args.blur_spread)
                for r, k in todo}
        made = {}
        for (r, k), f in futs.items():
            made[(r, k)] = f.result()
            d = made[(r, k)]
            print(f"design {k} for {r}: loss {d['final']['loss']:.4f}, misses {100 * d['final']['miss_rate']:.2f}%, "
                  f"{d['timings']['total_s']:.1f} s", flush=True)
    design_wall = time.perf_counter() - t0
    stem = args.stem or f"designed-patterns-{'cuda' if cuda else 'cpu'}"
    sweep_argv = ["--presets", args.presets, "--designs", str(designs), "--seed", str(args.seed),
                  "--neural-frames", ",".join(([] if args.without_random6 else ["random6"]) + [f"design{k}" for k in counts]),
                  "--out", str(out), "--stem", f"{stem}-sweep", "--state", str(out / f"{stem}-state")]
    sweep_argv += ["--rigs", ",".join(args.rigs.split(","))] if args.rigs else []
    sweep_argv += ["--small"] if args.small else []
    sweep_argv += ["--scenes", args.scenes] if args.scenes else []
    sweep_argv += ["--max-minutes", str(args.max_minutes)] if args.max_minutes else []
    sweep_argv += ["--workers-per-gpu", str(args.workers_per_gpu)] if cuda else ["--workers", str(args.workers or 1)]
    rc = accuracy_sweep.main(sweep_argv)
    sweep = json.loads((out / f"{stem}-sweep.json").read_text())
    doc = {"date": datetime.date.today().isoformat(), "device_name": sweep["device_name"],
           "command": " ".join(["python -m bench.designed_patterns"] + list(sys.argv[1:] if argv is None else argv)),
           "designs": {f"{r}/design{k}": {"final": d["final"], "timings": d["timings"], "hypotheses": d["hypotheses"],
                                          "device": d["device"]} for (r, k), d in made.items()},
           "design_wall_s": design_wall, "targets": targets(sweep, rigs, counts, args.presets.split(","))}
    (out / f"{stem}.json").write_text(json.dumps(doc, indent=1, default=float) + "\n")
    text = markdown(doc, sweep, stem)
    (out / f"{stem}.md").write_text(text)
    print(text)
    return rc


def targets(sweep: dict, rigs: list[str], counts: list[int], presets: list[str]) -> dict:
    """Per rig and preset: mean MAE of each set, designed 4 / random 6 (<= 1) and designed 3 / GC(7)-interp (<= 1)."""
    t = sweep["table"]
    out = {}
    for r in rigs:
        gc7 = t[r].get("GC(7) interp", {}).get("mean", {})
        for p in presets:
            row = {"GC(7) interp": gc7.get("mae"), "GC(6) interp": t[r].get("GC(6) interp", {}).get("mean", {}).get("mae")}
            for fs in ["random6"] + [f"design{k}" for k in counts]:
                m = t[r].get(f"{p} on {fs}", {}).get("mean", {})
                row[fs] = m.get("mae")
                row[fs + " complete"] = m.get("completeness")
            if row.get("design4") and row.get("random6"):
                row["design4 / random6"] = row["design4"] / row["random6"]
            if row.get("design3") and row.get("GC(7) interp"):
                row["design3 / GC(7)"] = row["design3"] / row["GC(7) interp"]
            out[f"{p} on {r}"] = row
    return out


def markdown(doc: dict, sweep: dict, stem: str) -> str:
    from slwarp.evaluation.metrics import format_table

    md = [f"# Designed patterns against random 6 and Gray code ({doc['device_name']}, {doc['date']})", "",
          f"`{doc['command']}`: one design per rig and count ({doc['design_wall_s'] / 60:.1f} min for all, several "
          f"designs at a time on one device), then `bench.accuracy_sweep` over every scene (tables: [{stem}-sweep.md]"
          f"({stem}-sweep.md)). Mean MAE (mm) over the scenes; targets: designed 4 <= random 6 with the same preset, "
          "designed 3 <= GC(7)-interp.", ""]
    sets = [k for k in next(iter(doc["targets"].values())).keys() if not k.endswith("complete") and "/" not in k]
    cols = [(k, k, "{:.3f}") for k in sets] + [("design4 / random6", "designed 4 / random 6", "{:.2f}"),
                                               ("design3 / GC(7)", "designed 3 / GC(7)", "{:.2f}")]
    md.append(format_table([(name, row) for name, row in doc["targets"].items()], cols, "preset on rig"))
    md += ["", "Completeness (share of the GT mask with depth):", ""]
    cc = [(k + " complete", k, "{:.1%}") for k in sets if not k.startswith("GC")]
    md.append(format_table([(name, row) for name, row in doc["targets"].items()], cc, "preset on rig"))
    md += ["", "The designs (validation loss and miss rate of the design objective, its own time):", ""]
    rows = [(k, {"loss": d["final"]["loss"], "miss": d["final"]["miss_rate"], "s": d["timings"]["total_s"],
                 "h": d["hypotheses"]}) for k, d in doc["designs"].items()]
    md.append(format_table(rows, [("loss", "loss", "{:.4f}"), ("miss", "misses", "{:.2%}"), ("h", "hypotheses", "{}"),
                                  ("s", "design s", "{:.1f}")], "rig/design"))
    return "\n".join(md) + "\n"


if __name__ == "__main__":
    os.environ.setdefault("PYTHONUNBUFFERED", "1")
    sys.exit(main())
