#!/usr/bin/env bash
set -uo pipefail
export PYTHONUNBUFFERED=1
mkdir -p $OUT/res
timeout 200 python3 -m pytest -q -k "cuda" tests/test_hashgrid.py 2>&1 | tee $OUT/tests.log | tail -40
timeout 300 python3 bench/bench_field.py --compile --out $OUT/res 2>&1 | tail -40
