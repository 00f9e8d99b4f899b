"""The depth search alone (the neural reconstruction's starting map) on simulated scans of several pattern sets, beside
Gray code: how well a set's codes tell depths apart before any training. For designed sets, each with the window step
it was designed for (`slwarp design-patterns --window-step S`) and with the plain window.

    python -m bench.search_only --rig default --scenes bunny,rods --designs 1:D1/patterns.yaml 3:D3/patterns.yaml
    python -m bench.search_only --smoke            # small rig, one scene, no design (a CPU smoke test)

Each scene is simulated once with random 6 + Gray code 7 (simulator seed 0), and once per designed set. The search is
the trainer's (`neural.start.search_start` with `fast`'s settings: 5 x 5 windows on every 2nd pixel, hypotheses 1 mm
apart, the patterns blurred by 1 px); GC(7) interp decodes the 7 Gray code images. Metrics against the scan's ground truth inside
its mask (MAE, median, share > 5 mm, completeness). Writes <out>/<stem>.json and .md and prints the table.
"""
from __future__ import annotations

import argparse
import datetime
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
from bench import markdown_table, write_study  # noqa: E402

METRICS = ("mae", "median", "over_5mm", "completeness")


def search(scan, names: list[str], step: int, device: str):
    """The trainer's starting search (`neural.start.search_start`, `fast`'s search settings) on the frames `names`
    of `scan`, windows `step` px apart: its depth map [H, W] (mm, NaN: none)."""
    import torch

    from slwarp.neural.config import preset
    from slwarp.neural.start import search_start, working_volume

    frames = scan.select(names)
    config = preset("fast", search_window_step=step, device=device)
    lit, _ = working_volume(frames, config, len(frames), frames.depth_range)
    return search_start(frames, config, len(frames), frames.depth_range, lit, frames.images, torch.device(device))[0]


def scores(depth, scan) -> dict:
    from slwarp.evaluation.metrics import depth_metrics

    m = depth_metrics(depth, scan.gt_depth, scan.mask)
    return {k: float(m[k]) for k in METRICS}


def run(rig: str, scenes: list[str], designs: list[tuple[int, str]], device: str, log=print,
        random6_steps: tuple[int, ...] = (1,)) -> dict:
    """{scene: {method: metrics}} (see the module docstring); random 6 searched with each of `random6_steps`."""
    from slwarp.decode import reconstruct_depth
    from slwarp.scans.patterns import named_set
    from slwarp.sim.simulate import simulate_scene

    out = {}
    for scene in scenes:
        t = time.perf_counter()
        base = simulate_scene(scene, "random6+gray7", rig=rig, device=device)
        rand = [n for n in base.names if n.startswith("rand")]
        rows = {("random 6, search" if s == 1 else f"random 6, search step {s}"): scores(search(base, rand, s, device), base)
                for s in random6_steps}
        gc, _, _ = reconstruct_depth(base, "gc-interp", frames="gray:col:bit=0-6:noinv")
        rows["GC(7) interp"] = scores(gc, base)
        for step, path in designs:
            scan = simulate_scene(scene, named_set(path, base.projector.width, base.projector.height), rig=rig,
                                  device=device)
            for s in sorted({1, step}):
                rows[f"{path} (designed for step {step}), search step {s}"] = scores(search(scan, scan.names, s, device),
                                                                                    scan)
        out[scene] = rows
        log(f"{scene}: {time.perf_counter() - t:.0f} s")
    return out


def markdown(doc: dict) -> str:
    lines = [f"# The depth search alone, {doc['rig']} rig, {doc['device']}, {doc['date']}", "", f"`{doc['bench_command']}`",
             "", __doc__.split("\n\n")[2].replace("\n", " "), ""]
    for scene, rows in doc["scenes"].items():
        lines += [f"## {scene}", ""]
        lines += markdown_table(["method", "MAE mm", "median mm", "> 5 mm", "complete"],
                                [[k, f"{m['mae']:.3f}", f"{m['median']:.3f}", f"{100 * m['over_5mm']:.2f}%",
                                  f"{100 * m['completeness']:.1f}%"] for k, m in rows.items()])
        lines.append("")
    return "\n".join(lines)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--rig", default="default")
    p.add_argument("--scenes", default="bunny,rods")
    p.add_argument("--designs", nargs="*", default=[], metavar="STEP:PATH",
                   help="designed sets: the window step each was designed for, and its patterns.yaml")
    p.add_argument("--random6-steps", default="1", help="window steps to search random 6 with, e.g. 1,2,3 (default 1)")
    p.add_argument("--device", default="cpu")
    p.add_argument("--smoke", action="store_true", help="small rig, spheres, no design")
    p.add_argument("--stem", default=None)
    p.add_argument("--out", default=str(REPO / "bench" / "results"))
    args = p.parse_args(argv)
    if args.smoke:
        args.rig, args.scenes = "small", "spheres"
    designs = []
    for d in args.designs:
        step, _, path = d.partition(":")
        if not step.isdigit() or int(step) < 1 or not path:
            raise SystemExit(f"--designs: {d!r} is not STEP:PATH (a window step >= 1, then a patterns.yaml)")
        designs.append((int(step), path))
    scenes = [s.strip() for s in args.scenes.split(",") if s.strip()]
    try:
        steps = tuple(int(s) for s in args.random6_steps.split(","))
    except ValueError:
        steps = ()
    if not steps or min(steps) < 1:
        raise SystemExit(f"--random6-steps: {args.random6_steps!r} is not a list of window steps >= 1 (e.g. 1,2,3)")
    doc = {"device": "CPU" if args.device == "cpu" else args.device, "date": str(datetime.date.today()), "rig": args.rig,
           "bench_command": "python -m bench.search_only " + " ".join(argv if argv is not None else sys.argv[1:]),
           "scenes": run(args.rig, scenes, designs, args.device, random6_steps=steps)}
    write_study(Path(args.out) / (args.stem or f"search-only-{args.rig}"), doc, lambda d: markdown(d) + "\n")


if __name__ == "__main__":
    main()
