#!/usr/bin/env bash
# The JAX engine's step on a GPU machine in one call: the `paper` preset's step timed
# and profiled at 96 robots (and the batches in BATCHES) under XLA's default flags, then timed
# with CUDA graphs around loops and conditionals, and with no CUDA graphs. Writes the JSON lines
# and each batch's kernel table (kernels.json) and compiled program under OUTDIR.
#
#   source .gpu-carry/env.sh; bash benchmarks/gpu_latency.sh OUTDIR [BATCHES] [EXTRA step_cost.py args]
set -u
out=${1:?OUTDIR}; batches=${2:-96}; shift $(( $# > 1 ? 2 : 1 ))
mkdir -p "$out"
nvidia-smi --query-gpu=name,clocks.sm,clocks.mem,memory.total --format=csv | tee -a "$out/log.txt"
run() {  # NAME XLA_FLAGS step_cost args...: JSON lines to results.jsonl, everything to log.txt
    local name=$1 flags=$2; shift 2
    echo "== $name (XLA_FLAGS=$flags)" | tee -a "$out/log.txt"
    XLA_FLAGS="$flags" timeout 300 python3 benchmarks/step_cost.py "$@" 2>>"$out/log.txt" \
        | sed "s/^{/{\"variant\": \"$name\", /" | tee -a "$out/results.jsonl"
}
run default "" --time --batches "$batches" --calls 10 --profile /tmp/prof "$@"
for b in /tmp/prof/b*; do gzip -c "$b/kernels.json" > "$out/kernels-$(basename "$b").json.gz"; gzip -c "$b/step.hlo.txt" > "$out/hlo-$(basename "$b").txt.gz"; done
run graphs "--xla_gpu_enable_command_buffer=FUSION,CUBLAS,CUBLASLT,CUSTOM_CALL,CUDNN,WHILE,CONDITIONAL --xla_gpu_graph_min_graph_size=1" --no-cost --time --batches 96 --calls 10 "$@"
run nographs "--xla_gpu_enable_command_buffer=" --no-cost --time --batches 96 --calls 10 "$@"
