#!/usr/bin/env bash
# One-time (idempotent) set-up: a virtual environment in .venv with slwarp and its dependencies.
# torch: an already installed build is kept; otherwise torch==2.13.0 is installed explicitly (on CPU-only
# machines of this project that is a local CPU wheel), so that no range ever pulls a CUDA build by itself.
set -euo pipefail
cd "$(dirname "$0")"
PY=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
  "$PY" -m venv .venv
fi
VPY=.venv/bin/python
stamp=.venv/.slwarp-installed
want=$(cat pyproject.toml setup.sh | sha1sum | cut -c1-16)
if [ -f "$stamp" ] && [ "$(cat "$stamp")" = "$want" ]; then
  exit 0
fi
export PIP_DISABLE_PIP_VERSION_CHECK=1
if ! "$VPY" -c "import torch" 2>/dev/null; then
  echo "setup: installing torch==2.13.0" >&2
  "$VPY" -m pip install -q "torch==2.13.0"
fi
echo "setup: installing slwarp and its dependencies into .venv" >&2
"$VPY" -m pip install -q -e ".[test]"
echo "$want" > "$stamp"
