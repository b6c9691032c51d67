#!/usr/bin/env bash
# One device call (bench/large_grids.md, "The second GPU session"): bundles, a step's time of the code in
# .base/rngcam (another checkout: `git archive REV rngcam | tar -x -C .base`, carried) then of this one, a
# profile, the GPU check rows, the device tests and audit. Results in $OUT (8 files at most come back).
set -u; PY=${PY:-python3}
T0=$(date +%s); DEV=${DEV:-cuda}; LIMIT=${LIMIT:-565}
el() { echo $(( $(date +%s) - T0 )); }
if [ -z "${SKIP_WHEELS:-}" ] && ls .whl/*.whl >/dev/null 2>&1; then
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || { echo "wheels failed"; exit 3; }
fi
export PYTHONPATH="/tmp/site:$PWD" PYTHONUNBUFFERED=1 PYTHONSAFEPATH=1  # -m would import ./rngcam before OLD
R=${OUT:-/tmp/gcout}; W=${W:-/tmp/gc}; mkdir -p $W $R
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader 2>/dev/null; nproc; uptime
for s in "sineball 64" "smoke 64" "smoke ${BIG:-228x342}"; do set -- $s
  [ -f $W/$1-$2.h5 ] || $PY -m rngcam simulate $1 --size $2 -o $W/$1-$2.h5 > $W/sim-$1-$2.log 2>&1 &
done
wait; ls $W; echo "== bundles @$(el)"; uptime
for v in base new; do
  PP=$PYTHONPATH; [ $v = base ] && PP="/tmp/site:$PWD/.base:$PWD"
  PYTHONPATH=$PP timeout 110 $PY -m bench.step_time $W/sineball-64.h5 $W/smoke-64.h5 --device $DEV --iters ${ITERS:-20,80} 2>&1 | grep -v USDT | tee $R/steps_$v.txt
  echo "== steps $v @$(el)"
done
timeout 80 $PY -m bench.step_time $W/sineball-64.h5 --device $DEV --iters 5,60 --profile $R/profile.txt 2>&1 | grep -v USDT | tail -4
echo "== profile @$(el)"; uptime
for only in "smoke ${BIG:-228x342}" "sineball 64,smoke 64"; do
  left=$(( LIMIT - $(el) )); [ $left -gt 30 ] || break
  timeout $left $PY -m bench.gpu_check -o $W --device $DEV ${QUICK:-} --skip-tests --only "$only" 2>&1 | grep -v USDT | tail -8
  tag=$(echo "$only" | cut -c1-5); cp $W/gpu_check.md $R/check_$tag.md
  echo "== check $only @$(el)"
done
left=$(( LIMIT - $(el) )); [ $left -gt 20 ] && timeout $left $PY -m pytest -q -p no:cacheprovider tests/test_operators.py 2>&1 | tail -2
left=$(( LIMIT - $(el) )); [ $left -gt 30 ] && timeout $left $PY -m bench.device_audit --device $DEV -o /tmp/audit > $R/audit.txt 2>&1
tail -c 300000 $W/gpu_check.log > $R/gpu_check.log; echo "done @$(el)"; uptime
