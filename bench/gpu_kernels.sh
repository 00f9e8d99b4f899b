#!/usr/bin/env bash
# On a lent GPU machine, from the repo root, with warp importable (see ../shared/gpu/README.md):
# the CUDA variants of the op/simulator tests, the kernel microbenchmark and the simulator timing.
# Results go to $OUT (the device tool brings them back) or bench/results.
set -uo pipefail
export PYTHONUNBUFFERED=1
OUT=${OUT:-bench/results}
python3 -m pip install -q --no-deps --no-build-isolation --no-index -e . >/dev/null 2>&1 || echo "pip -e failed"
nvidia-smi --query-gpu=name,memory.total,driver_version,clocks.sm --format=csv
python3 -m pytest -q tests/test_ops.py tests/test_simulate.py tests/test_scanner.py -k "cuda or compile" 2>&1 | tee "$OUT/gpu-tests.log" | tail -4
python3 bench/bench_simulate.py --out "$OUT" 2>&1 | tail -12
python3 bench/bench_kernels.py --out "$OUT" 2>&1 | tee "$OUT/bench-kernels.log" | grep -v '^{' | tail -20
