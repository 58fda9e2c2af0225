#!/usr/bin/env bash
# Issue 7's GPU figures, for one lent H100/H200 (run from the repository root):
#
#   bash benchmarks/gpu_suite.sh OUTDIR [STEP ...]      # default: every step, in this order
#
# Steps (and what each took on an H200 on 2026-11-30, compile included):
#   bench_bf16  forward at the paper's Table-6 window (B=1 T=20 720x1280 iters=20), bfloat16,
#               the default ViT attention ("auto": cuDNN's fused kernel on a GPU)  (68 s)
#   bench_fp32  the same in float32 (XLA's default matmul precision: TF32 on the GPU)  (87 s);
#               its program goes to the compilation cache OUTDIR/xla_cache
#   bench_fp32_warm  bench_fp32 again, its program loaded from OUTDIR/xla_cache (run it after
#               bench_fp32): no autotuner runs, so the device peak is the program's, as in a
#               second `sav-jax infer` run (bench_fp32's 29.9 GB peak on 2026-11-30 was the
#               autotuner's scratch; the program's buffers are 9.4 GB)
#   bench_blocked  bench_bf16 with the blocked softmax ViT attention (--vit-attention blocked)
#   train       the training step at the paper's shape (T=5 256x512 iters=10, remat)  (118 s on
#               2026-12-04); its program goes to the compilation cache OUTDIR/xla_cache
#   train_warm  train again, loaded from OUTDIR/xla_cache (run it after train): the step's own
#               device peak, without the autotuner's (4.14 GB against 25.6 GB on 2026-12-04)
#               (~25 s)
#   precision   distance from the official output per compute mode (precision_check.py;
#               needs SAV_FIXTURES)    (143 s on 2026-11-30; > 200 s on 2026-12-04's machine)
#   parity      the end-to-end parity tests on this backend (needs SAV_FIXTURES)        (> 150 s)
#   stages      per-stage wall times at the paper's window, bfloat16 (stage_times.py)  (106 s)
#   profile     per-module GPU time, multiply-adds and rate, bfloat16 (op_profile.py)  (75 s)
#   variants    candidate rewrites of the update block's parts and the ViT attention, timed
#               against the model's modules at the paper's window (update_variants.py)
#   raft        the evaluator's RAFT flow for one 720x1280 pair, 20 iterations (raft_flow.py)
#               and its parity tests (tests/model/test_raft.py; needs SAV_FIXTURES); not in
#               the default list
#   gru_conv    the GRU's 1x15 convolutions as XLA's or as DFT products (SAVConfig.gru_conv,
#               "auto" picks DFT products on CPUs only: not yet measured on a GPU): the GRU at
#               each scale of the paper's window (gru_conv.py, float32 and bfloat16), then the
#               float32 window with --gru-conv dft. Not in the default list (~4 minutes)
#   flags       bench_bf16 (2 calls) under XLA:GPU flag sets that may speed up the refinement
#               loop (~75 s each, compile included): command buffers off / over the whole
#               loop and its conditional, cuBLAS instead of Triton for the products, the
#               exhaustive Triton tiling search; one JSON per set. Not in the default list
#               (5 sets: ~7 minutes); `FLAG_SETS="name=flags;..."` replaces the sets
# A lease of 15 device minutes holds about 13 minutes of steps (a start took ~30 s); the
# default list took ~19-20 minutes on 2026-11-30, so pick the steps. Each step has its own time limit; everything is logged to OUTDIR/suite.log and
# the figures go to OUTDIR/*.json. A failure of the first step within 90 s (an import or API
# error) stops the run, so that the rest of a short lease is not spent; the exit status is 1
# when any step failed or JAX finds no GPU (before any step runs), 2 for an unknown step name
# (before anything runs). Rerunning a step
# into the same OUTDIR replaces its JSON.
set -u
out=${1:?usage: bash benchmarks/gpu_suite.sh OUTDIR [STEP ...]}
shift
steps=("$@")
[ ${#steps[@]} -eq 0 ] && steps=(bench_bf16 bench_fp32 bench_fp32_warm train train_warm precision parity stages variants profile bench_blocked)
known=" bench_bf16 bench_fp32 bench_fp32_warm bench_blocked train train_warm precision parity stages profile variants raft flags gru_conv "
for s in "${steps[@]}"; do  # a mistyped step fails before anything runs (no OUTDIR, no import)
  if [[ "$known" != *" $s "* ]]; then
    echo "unknown step '$s' (${known# })" >&2
    exit 2
  fi
done

mkdir -p "$out"
export PYTHONUNBUFFERED=1
py=${PYTHON:-python3}
log="$out/suite.log"
window=(--frames 20 --height 720 --width 1280 --iters 20)
# The `flags` step's sets, "name=XLA flags" separated by ';' (the default set is the baseline).
flag_sets=${FLAG_SETS:-"default=;cmdbuf_off=--xla_gpu_enable_command_buffer=;\
cmdbuf_loop=--xla_gpu_enable_command_buffer=FUSION,CUBLAS,CUBLASLT,CUSTOM_CALL,CUDNN,CONDITIONAL,WHILE \
--xla_gpu_graph_min_graph_size=1;cublas=--xla_gpu_enable_triton_gemm=false;\
exhaustive=--xla_gpu_exhaustive_tiling_search=true"}

step() {  # step NAME LIMIT_S COMMAND...
  local name=$1 limit=$2 t0=$SECONDS rc
  shift 2
  echo "=== $name ($(date +%T), limit ${limit} s): $*" | tee -a "$log"
  timeout "$limit" "$@" 2>&1 | grep --line-buffered -v "cuda_timer.cc" | tee -a "$log"
  rc=${PIPESTATUS[0]}
  echo "=== $name: rc=$rc after $((SECONDS - t0)) s" | tee -a "$log"
  return "$rc"
}

run_step() {
  case $1 in
    bench_bf16) step "$1" 150 "$py" -m sav_jax.cli bench "${window[@]}" --dtype bfloat16 \
                  --repeats 3 --json "$out/gpu_t20_720x1280_it20_bf16.json" --overwrite ;;
    bench_fp32) step "$1" 150 "$py" -m sav_jax.cli bench "${window[@]}" --dtype float32 \
                  --repeats 2 --compile-cache "$out/xla_cache" \
                  --json "$out/gpu_t20_720x1280_it20_fp32.json" --overwrite ;;
    bench_fp32_warm) step "$1" 120 "$py" -m sav_jax.cli bench "${window[@]}" --dtype float32 \
                  --repeats 2 --compile-cache "$out/xla_cache" \
                  --json "$out/gpu_t20_720x1280_it20_fp32_warm.json" --overwrite ;;
    bench_blocked) step "$1" 150 "$py" -m sav_jax.cli bench "${window[@]}" --dtype bfloat16 \
                  --vit-attention blocked --repeats 3 \
                  --json "$out/gpu_t20_720x1280_it20_bf16_blocked.json" --overwrite ;;
    train) step "$1" 260 "$py" benchmarks/train_step.py --repeats 2 --compile-cache "$out/xla_cache" \
             --json "$out/gpu_train_t5_256x512_it10_remat_fp32.json" --overwrite ;;
    train_warm) step "$1" 120 "$py" benchmarks/train_step.py --repeats 2 \
                  --compile-cache "$out/xla_cache" \
                  --json "$out/gpu_train_t5_256x512_it10_remat_fp32_warm.json" --overwrite ;;
    precision) step "$1" 330 "$py" benchmarks/precision_check.py --json "$out/gpu_precision.json" --overwrite ;;
    parity) step "$1" 300 "$py" -m pytest -x -q -p no:cacheprovider \
              tests/model/test_model_parity.py ;;
    stages) step "$1" 300 "$py" benchmarks/stage_times.py "${window[@]}" --dtype bfloat16 ;;
    variants) step "$1" 300 "$py" benchmarks/update_variants.py "${window[@]}" --dtype bfloat16 ;;
    profile) step "$1" 240 "$py" benchmarks/op_profile.py "${window[@]}" --dtype bfloat16 \
               --repeats 1 --by module --depth 2 --top 25 ;;
    gru_conv) step "$1" 300 bash -c "'$py' benchmarks/gru_conv.py --frames 20 --height 720 --width 1280 --repeats 3 &&
                '$py' benchmarks/gru_conv.py --frames 20 --height 720 --width 1280 --repeats 3 --dtype bfloat16 &&
                '$py' -m sav_jax.cli bench ${window[*]} --dtype float32 --gru-conv dft --repeats 2 \
                  --json '$out/gpu_t20_720x1280_it20_fp32_gru_dft.json' --overwrite" ;;
    raft) step "$1" 200 bash -c "'$py' benchmarks/raft_flow.py --height 720 --width 1280 &&
            '$py' -m pytest -x -q -p no:cacheprovider tests/model/test_raft.py" ;;
    flags) local set name rc=0
           IFS=';' read -ra sets <<< "$flag_sets"
           for set in "${sets[@]}"; do
             name=${set%%=*}
             XLA_FLAGS="${XLA_FLAGS:-} ${set#*=}" step "flags_$name" 130 "$py" -m sav_jax.cli \
               bench "${window[@]}" --dtype bfloat16 --repeats 2 \
               --json "$out/gpu_t20_720x1280_it20_bf16_flags_$name.json" --overwrite || rc=$?
           done
           return "$rc" ;;
    *) echo "unknown step '$1' (bench_bf16 bench_fp32 bench_fp32_warm bench_blocked train train_warm precision parity" \
            "stages profile variants raft flags)" >&2
       return 2 ;;
  esac
}

{
  nvidia-smi --query-gpu=name,memory.total,driver_version,clocks.sm,clocks.max.sm --format=csv
  "$py" -c "import jax, flax, optax; print('jax', jax.__version__, 'flax', flax.__version__,
'optax', optax.__version__, jax.devices())"
} 2>&1 | tee -a "$log"
# The steps are a GPU's figures: on a CPU (or with a jaxlib without CUDA) each would run out
# its time limit compiling the paper's window, for half an hour in all.
"$py" -c "import sys, jax; b = jax.default_backend(); b == 'gpu' or sys.exit(
    f'no GPU: JAX in {sys.executable} runs on {b} (a jaxlib without CUDA?); no step run')" \
  2>&1 | tee -a "$log"
[ "${PIPESTATUS[0]}" = 0 ] || exit 1

first=1
status=0
for s in "${steps[@]}"; do
  if ! run_step "$s"; then
    status=1
    if [ "$first" = 1 ] && [ "$SECONDS" -lt 90 ]; then
      echo "early failure: stopping" | tee -a "$log"
      exit 1
    fi
  fi
  first=0
done
echo "=== done after $SECONDS s$([ "$status" = 0 ] || echo ', some steps failed')" | tee -a "$log"
exit "$status"
