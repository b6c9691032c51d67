#!/usr/bin/env bash
# The GPU check in one call (bench/gpu_check.py): run from the repository root on a lent GPU.
# Wheels the GPU image lacks (pydantic and its parts) may be carried in .whl/; they are installed
# into /tmp/site first. Everything lands in ${OUT:-gpu-check-out}; the table is printed at the end.
set -uo pipefail
cd "$(dirname "$0")/.."
if ls .whl/*.whl >/dev/null 2>&1; then
    python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl \
        && export PYTHONPATH="/tmp/site:${PYTHONPATH:-}"
fi
export PYTHONPATH="$PWD:${PYTHONPATH:-}" PYTHONUNBUFFERED=1
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader 2>/dev/null || echo "no nvidia-smi"
exec python3 -m bench.gpu_check -o "${OUT:-gpu-check-out}" "$@"
