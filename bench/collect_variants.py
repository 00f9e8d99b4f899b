"""Merge the per-variant JSON files of bench/train_variants.py into one file (name -> result).

    python bench/collect_variants.py VARIANTS_DIR OUT.json
"""
import json
import sys
from pathlib import Path

src, dst = Path(sys.argv[1]), Path(sys.argv[2])
merged = {f.stem: json.loads(f.read_text()) for f in sorted(src.glob("*.json"))}
dst.write_text(json.dumps(merged, indent=1))
print(f"{len(merged)} results -> {dst}")
