#!/usr/bin/env bash
# On a lent GPU machine, from the repo root, with warp importable (see ../shared/gpu/README.md): the issue-6
# benchmarks in stages that each fit one 10-minute device call. Results go to $OUT as one tarball per stage
# (bench/results/ layout), plus the stage's log.
#   bash bench/gpu_paper.sh speed      # graph test on CUDA, training speed per config with the breakdown
#   bash bench/gpu_paper.sh e2e        # loaded scan -> depth map, backend warp and torch (paper preset)
#   (seeds 1, 2 of both backends: bench/train_variants.py NAME:scene=bunny,preset=paper,backend=B,seed=S)
#   bash bench/gpu_paper.sh table1     # Table 1, six scenes, tuned preset, 6 runs side by side
#   bash bench/gpu_paper.sh ablation   # Table 2 (bunny, 2000 iterations) and Fig. 8, 7 runs side by side
#   bash bench/gpu_paper.sh fig7       # Fig. 7, K = 3, 5, 7, 9 with and without inverses, 2000 iterations
set -uo pipefail
export PYTHONUNBUFFERED=1
OUT=${OUT:-/tmp/slwarp-out}
RES=/tmp/slwarp-results
mkdir -p "$OUT" "$RES"
python3 -m pip install -q --no-deps --no-build-isolation --no-index -e . >/dev/null 2>&1 || echo "pip -e failed"
stage=${1:?stage: speed, e2e, table1, ablation or fig7}
limit=${LIMIT:-540}
case "$stage" in
  speed)
    nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader
    timeout 150 python3 -m pytest -q -x tests/test_train.py -k cuda_graph 2>&1 | tail -15
    timeout $((limit - 160)) python3 bench/train_speed.py --out "$RES" 2>&1 | grep -v '^{' ;;
  e2e)
    timeout "$limit" python3 bench/train_speed.py --configs --end-to-end --out "$RES" 2>&1 | grep -v '^{' ;;
  table1)
    timeout "$limit" python3 bench/paper_experiments.py table1 --preset tuned --parallel 6 --out "$RES" --work /tmp/work 2>&1 ;;
  ablation)
    timeout "$limit" python3 bench/paper_experiments.py ablation --preset tuned --iters 2000 --parallel 5 --out "$RES" --work /tmp/work 2>&1 &
    sleep 20  # let the ablation's processes start first
    timeout $((limit - 20)) python3 bench/paper_experiments.py fig8 --preset tuned --parallel 2 --out "$RES" --work /tmp/work 2>&1 &
    wait ;;
  fig7)
    timeout "$limit" python3 bench/paper_experiments.py fig7 --preset tuned --ks 3,5,7,9 --iters 2000 --parallel 8 \
      --out "$RES" --work /tmp/work 2>&1 ;;
  *) echo "unknown stage $stage"; exit 2 ;;
esac
tail -n 3 /tmp/work/*/*.log 2>/dev/null | tail -40
tar czf "$OUT/$stage.tgz" -C "$RES" . 2>/dev/null
ls -la "$OUT"
