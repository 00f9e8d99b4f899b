"""Table: the neural SDF (paper and tuned presets, GPU runs of bench/train_variants.py) next to the classical
baselines (bench/classical_baselines.py) on the six built-in scenes, default rig and noise.

    python bench/six_scene_table.py [--neural bench/results/neural-variants-cuda.json]
                                    [--classical bench/results/classical-cpu.json]
Writes bench/results/six-scenes.md. Runs named paper_<scene> / tuned_<scene> are picked up; the bunny
runs V1 (paper) and V2 (tuned settings) come from the first tuning batch.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SCENES = ("spheres", "torus", "boxes", "bunny", "vase", "steps")
ALIASES = {("paper", "bunny"): "V1", ("tuned", "bunny"): "V2"}


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--neural", default=str(REPO / "bench/results/neural-variants-cuda.json"))
    p.add_argument("--classical", default=str(REPO / "bench/results/classical-cpu.json"))
    p.add_argument("--table1", default=str(REPO / "bench/results/table1-cuda.json"),
                   help="runs of bench/paper_experiments.py table1 (the current code; scenes it did not run show '-')")
    p.add_argument("--out", default=str(REPO / "bench/results/six-scenes.md"))
    args = p.parse_args(argv)
    neural = json.loads(Path(args.neural).read_text())
    classical = json.loads(Path(args.classical).read_text())["per_scene"]

    def ours(preset, scene):
        key = ALIASES.get((preset, scene), f"{preset}_{scene}")
        return neural.get(key, {}).get("metrics")

    methods = [("GC(6) interp", lambda s: classical["GC(6) interp"].get(s)),
               ("GC(7) interp", lambda s: classical["GC(7) interp"].get(s)),
               ("ours, paper preset", lambda s: ours("paper", s)),
               ("ours, tuned preset", lambda s: ours("tuned", s))]
    t1 = json.loads(Path(args.table1).read_text()) if Path(args.table1).is_file() else None
    if t1:
        label = f"ours, tuned + fitted pattern blur ({t1['device']})"
        methods.append((label, lambda s: t1["runs"].get(f"t1_{s}", {}).get("metrics")))
    device = next(iter(neural.values()))["device"]
    lines = [f"# Six built-in scenes, default rig and noise: neural SDF (6 random patterns) vs Gray code", "",
             f"Neural runs on the GPU: {device} (paper and tuned preset rows), "
             f"{t1['device'] if t1 else '-'} (last row).", "",
             "Classical rows from bench/results/classical-cpu.json. Rows 'paper preset' and 'tuned preset': "
             "bench/results/neural-variants-cuda.json, runs of the earlier code (the renderer sampled the sharp patterns, "
             "no photometric check). Last row: bench/results/table1-cuda.json, the current code (pattern blur fitted "
             "to the images, photometric check, training step as a CUDA graph), run on "
             f"{t1['date'] if t1 else '-'} for the scenes " + (", ".join(s for s in SCENES if f"t1_{s}" in t1["runs"]) if t1 else "-")
             + " ('-' where a scene was not run).", ""]
    for key, title, fmt in (("mae", "MAE (mm)", "{:.3f}"), ("median", "median |error| (mm)", "{:.3f}"),
                            ("over_5mm", "share of pixels with |error| > 5 mm", "{:.2%}"),
                            ("completeness", "completeness", "{:.1%}")):
        lines += [f"## {title}", "", "| method | " + " | ".join(SCENES) + " | mean |", "|---" * (len(SCENES) + 2) + "|"]
        means = {}
        for name, get in methods:
            vals = [get(s)[key] if get(s) else None for s in SCENES]
            ok = [v for v in vals if v is not None]
            mean = sum(ok) / len(ok) if ok else None  # over the scenes that ran
            means[name] = mean
            cells = [fmt.format(v) if v is not None else "-" for v in vals] + [fmt.format(mean) if mean is not None else "-"]
            lines.append(f"| {name} | " + " | ".join(cells) + " |")
        if key == "mae":
            lines.append("")
            for name, get in methods[2:]:
                ran = [sc for sc in SCENES if get(sc)]
                if not ran:
                    continue
                m = {n: sum(g(sc)["mae"] for sc in ran) / len(ran) for n, g in methods if all(g(sc) for sc in ran)}
                lines.append(f"- {name}: mean MAE over {', '.join(ran) if len(ran) < len(SCENES) else 'the six scenes'} "
                             f"{m[name]:.3f} mm = {m[name] / m['GC(7) interp']:.2f}x GC(7) interp, "
                             f"{m[name] / m['GC(6) interp']:.2f}x GC(6) interp (targets: 0.6x and 0.4x)")
        lines.append("")
    text = "\n".join(lines)
    print(text)
    Path(args.out).write_text(text)


if __name__ == "__main__":
    main()
