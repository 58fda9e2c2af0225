#!/usr/bin/env bash
# Issue 7's GPU figures in one run, for one lent H100/H200 (run from the repository root):
#
#   bash benchmarks/gpu_suite.sh OUTDIR
#
# 1. forward at the paper's Table-6 window (B=1 T=20 720x1280 iters=20), bfloat16;
# 2. the same in float32 (XLA's default matmul precision: TF32 on the GPU);
# 3. the training step at the paper's shape (T=5 256x512 iters=10, remat);
# 4. distance from the official output per compute mode (benchmarks/precision_check.py);
# 5. the end-to-end parity tests on this backend (needs the oracle fixtures, SAV_FIXTURES).
# Each step has its own time limit; everything is logged to OUTDIR/suite.log and the
# figures go to OUTDIR/*.json. An early failure of step 1 (an import or API error) stops
# the run, so that a short device lease is not spent on the rest.
set -u
out=${1:?usage: bash benchmarks/gpu_suite.sh OUTDIR}
mkdir -p "$out"
export PYTHONUNBUFFERED=1
py=${PYTHON:-python3}
log="$out/suite.log"

step() {  # step NAME LIMIT_S COMMAND...
  local name=$1 limit=$2 t0=$SECONDS rc
  shift 2
  echo "=== $name ($(date +%T), limit ${limit} s): $*" | tee -a "$log"
  timeout "$limit" "$@" 2>&1 | tee -a "$log"
  rc=${PIPESTATUS[0]}
  echo "=== $name: rc=$rc after $((SECONDS - t0)) s" | tee -a "$log"
  return "$rc"
}

{
  nvidia-smi --query-gpu=name,memory.total,driver_version,clocks.sm,clocks.max.sm --format=csv
  "$py" -c "import jax, flax, optax; print('jax', jax.__version__, 'flax', flax.__version__,
'optax', optax.__version__, jax.devices())"
} 2>&1 | tee -a "$log"

window=(--frames 20 --height 720 --width 1280 --iters 20)
step bench_bf16 170 "$py" -m sav_jax.cli bench "${window[@]}" --dtype bfloat16 --repeats 3 \
    --json "$out/gpu_t20_720x1280_it20_bf16.json" \
  || { if [ "$SECONDS" -lt 90 ]; then echo "early failure: stopping" | tee -a "$log"; exit 1; fi; }
step bench_fp32 150 "$py" -m sav_jax.cli bench "${window[@]}" --dtype float32 --repeats 2 \
    --json "$out/gpu_t20_720x1280_it20_fp32.json"
step train_step 150 "$py" benchmarks/train_step.py --repeats 3 \
    --json "$out/gpu_train_t5_256x512_it10_remat_fp32.json"
step precision 90 "$py" benchmarks/precision_check.py --json "$out/gpu_precision.json"
step parity 150 "$py" -m pytest -x -q -p no:cacheprovider tests/model/test_model_parity.py
echo "=== done after $SECONDS s" | tee -a "$log"
