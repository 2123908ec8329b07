#!/usr/bin/env bash
# The GPU measurements, each a stage that fits one 10-minute device call; results (JSON lines,
# logs, gzipped kernel tables) under OUTDIR. Run the stages back to back on the warm machine, the
# open ones first, and record the figures in benchmarks/RESULTS.md with the card:
#
#   source .gpu-carry/env.sh; bash benchmarks/gpu_checks.sh OUTDIR candidates   # ~9 min, first
#   source .gpu-carry/env.sh; bash benchmarks/gpu_checks.sh OUTDIR elimination  # ~4 min, if candidates ran out of time
#   source .gpu-carry/env.sh; BASE=DIR bash benchmarks/gpu_checks.sh OUTDIR blocks   # ~4 min
#   source .gpu-carry/env.sh; bash benchmarks/gpu_checks.sh OUTDIR factors      # ~4 min, after candidates
#   source .gpu-carry/env.sh; bash benchmarks/gpu_checks.sh OUTDIR selection    # ~4 min
#   source .gpu-carry/env.sh; bash benchmarks/gpu_checks.sh OUTDIR parts        # ~6 min
#   source .gpu-carry/env.sh; [BASE=DIR] bash benchmarks/gpu_checks.sh OUTDIR rid   # ~8 min
#   source .gpu-carry/env.sh; bash benchmarks/gpu_checks.sh OUTDIR solve        # ~8 min
#   source .gpu-carry/env.sh; bash benchmarks/gpu_checks.sh OUTDIR crossover    # ~6 min
#   source .gpu-carry/env.sh; bash benchmarks/gpu_checks.sh OUTDIR profile      # ~5 min
#   source .gpu-carry/env.sh; bash benchmarks/gpu_checks.sh OUTDIR flags        # ~5 min
#   source .gpu-carry/env.sh; bash benchmarks/gpu_checks.sh OUTDIR attribution  # ~5 min
#   source .gpu-carry/env.sh; bash benchmarks/gpu_checks.sh OUTDIR kernels      # ~5 min
#   source .gpu-carry/env.sh; bash benchmarks/gpu_checks.sh OUTDIR groundtruth  # ~9 min
#   source .gpu-carry/env.sh; bash benchmarks/gpu_checks.sh OUTDIR targets      # ~6 min, measured on an H100
#   source .gpu-carry/env.sh; bash benchmarks/gpu_checks.sh OUTDIR training     # ~6 min, measured on an H100
#
# candidates:  the step at 96 and 16,384 robots, float32, with the forms not yet defaults and
#              without: the defaults, all five together (the issue's figures if all are taken:
#              the RID kernel, the held solve, the unrolled factor, the contact candidates by one
#              kernel a robot, the attachments' elimination by one kernel a robot), the first
#              four together (what the elimination kernel adds), the RID kernel alone
#              (`--rid-form kernel`: the largest kernel; the held solve alone: `solve`, the
#              unrolled factor alone: `factors`, the candidates' kernel alone: `selection`); one
#              call, so that the forms are compared on one warm card, on the same robots: each
#              form's disk nodes after its four actions against the defaults' (`--reference`:
#              `reference_p99_robot_distance_mm`, the robots invalid in one run only), in order
#              of what they decide, a form the call has no time for left undecided. A form faster
#              at both sizes whose robots end
#              within 0.5 mm of the defaults' (99th percentile; the issue's budget between the
#              engines over 2 s; two float32 forms on the CPU differ by 0.04 mm at most) and
#              with no robot invalid that the defaults keep becomes the default: its results are
#              checked on the card, `rid` and `solve` add the kernels' own checks and variants.
#              First, `softcrawl verify --only jax_incline` (OUTDIR/verify.json): the solve's
#              kernel on the card against the box-on-incline closed form (seconds).
# elimination: the step at 96 and 16,384 robots with the attachments' elimination in one kernel
#              (`--elimination kernel`, softcrawl.jaxsim.elimination: 7 operations fewer, 0.57 MB
#              less a robot-step, compiled for an H100) against XLA's products, both with the four
#              candidates' forms, on the same robots, alone in its call (`candidates` compares the
#              two after the defaults); if faster at both sizes, make "kernel"
#              `elimination.FORM`'s default.
# blocks:      the step at 96 and 16,384 robots with the factor kernels holding their matrices in
#              blocks (factor.row_parts, the defaults) against BASE's, a commit before them whose
#              kernels held them padded (`mkdir -p .gpu-carry/base && git archive 508c788 softcrawl
#              | tar -x -C .gpu-carry/base`, then BASE=.gpu-carry/base), on the same robots, one
#              call: if the verdict makes {"label": "base"} the default, the padded kernels were
#              the faster: restore them (factor.py's kernels as of 508c788).
# selection:   the step at 96 and 16,384 robots with each robot's contact candidates chosen by one
#              kernel (`--selection kernel`, softcrawl.jaxsim.candidates, the warm start with
#              them: 16 operations fewer, 0.55 MB less a robot-step, compiled for an H100)
#              against the defaults, on the same robots; if faster at both sizes, make "kernel"
#              `candidates.SELECTION`'s default.
# factors:     the legs' 36 x 36 factors alone at 96 and 16,384 robots (`cholesky_kernel.py
#              --sizes 36`): first each leg's step matrix formed, factored and its free motion
#              solved in one kernel program (`step_solve`, the step's form) against XLA forming
#              the matrix and multiplying around the factor's kernel (`step_split_ms`); then the
#              kernel with its pivots looped and unrolled against the library, short enough for
#              the minutes `candidates` leaves. If the split form is faster at both sizes, set
#              `factor.STEP_IN_KERNEL = False`; if an unrolled variant is faster at both sizes,
#              `factor.UNROLL_PIVOTS = 36` (and `PER_THREAD` if 128 wins); the attachment
#              block's 72 x 72 inverse unrolled: `crossover`.
# parts:       the solve kernel reading the condensed operator in its parts (`fused.OPERATOR_PARTS`,
#              the default, counted but not timed on a card): the step at 96 and 16,384 robots
#              with it and with the operator formed by XLA first (`--formed-operator`), in one
#              call; then two actions of the whole engine with the kernel against XLA's
#              iterations (`fused_kernel.py`'s rollout: the engine's operator in its parts). If
#              the formed operator is faster at both sizes, set `fused.OPERATOR_PARTS = False`.
# rid:         the legs' RID terms in one kernel (`--rid-form kernel`, not yet a default): against
#              XLA's pairs and rows forms on the card and timed alone with its variants
#              (`rid_kernel.py`: if a variant other than the default, 16 elements, 2 warps, `Z`
#              in bfloat16 parts (SPLIT_BF16; SPLIT_TF32 its TF32 parts), one program a leg, its
#              rows in one group (3: fewer registers), column tiles of 16 (32: half the products
#              a warp, twice the per-element work), is fastest, set ridkernel.ELEMENTS / NUM_WARPS /
#              DOT_ALGORITHM / SPLIT / ROW_GROUPS / TILE), then
#              the step at 96 and 16,384 robots with it and without it, in one call; if faster at
#              both, make it the CUDA default (`legs.rid_terms`' None). BASE, where given, is a
#              folder holding an earlier commit's `softcrawl` package, put first on PYTHONPATH
#              (`mkdir -p .gpu-carry/base && git archive COMMIT softcrawl | tar -x -C
#              .gpu-carry/base`, then BASE=.gpu-carry/base): its step is timed in the same call,
#              on the same robots, and the verdict names it where it was the faster.
# solve:       the solve kernel holding its operator on chip, its products on the tensor cores
#              (`fused.RESIDENT_ROWS`, not yet a default): against XLA's iterations on 96 landed
#              robots' problems and two actions of the whole engine with it (`fused_kernel.py
#              --resident-rows 128`), the solve alone at 96 and 16,384 robots in each of the
#              kernel's variants; then the step at both sizes with it and without it, on the same
#              robots (`candidates` has it among the five and the four): if the step is faster with
#              it at both sizes, make 128 the default (or the fastest held variant's).
# crossover:   the legs' factors and the attachment block's inverse alone at 96, 1,024, 2,048,
#              4,096 and 16,384 robots, each kernel against the library (`cholesky_kernel.py`):
#              the kernels hold their matrices in blocks (factor.row_parts) and
#              `factor.LIBRARY_FROM` is None (the kernel at every batch, by its instruction
#              count); if the library's inverse is faster from some batch on, set it there;
#              the kernels with their pivots unrolled too (`*_unrolled_ms`): if faster at 96
#              and 16,384 robots, set `factor.UNROLL_PIVOTS` (36: the legs' kernel only, 72: both) and `PER_THREAD`.
# profile:     the step at 1,024 and 16,384 robots without CUDA graphs, every kernel timed
#              (`step_cost.py --profile`): where the large batches' time goes.
# flags:       the step at 96 and 16,384 robots with XLA's matrix products by cuBLAS only
#              (`--xla_gpu_enable_triton_gemm=false`) against XLA's defaults, on the same robots:
#              the device pads the operands of the products it gives to Triton (13 padding
#              kernels, 155 us of an earlier 96-robot step, absent from the program compiled
#              without a GPU): what they cost at both sizes, and so whether the products are
#              worth shaping to Triton's tiles (or the flag worth documenting for GPU runs).
# attribution: the step at 96 robots with each kernel alone (`fused16` with the library's
#              factors, `dense16` with the kernels'); the solve kernel's variants alone at 16,384
#              robots (occupancy decides there).
# kernels:     the step at 96 and 1,024 robots with the Delassus operator read in float32
#              (`--delassus dense`: the float16 operator against it), then every kernel of
#              the 96-robot step timed without CUDA graphs (kernels-b96, and the device's
#              compiled program, step-b96.hlo.txt, which names what each kernel fuses).
# groundtruth: the all-designs ground truth's rate on 256 sampled designs and its projection
#              for the 6,972 (`groundtruth.py rate`).
# targets:     the issue's two figures in one call: the step, float32, at 96 robots (1.5 ms) and
#              16,384 (250k robot-steps/s, about 0.07 s a step) with XLA's solve and the
#              library's factors (`--delassus dense16 --cholesky library`) and with the
#              defaults (the kernels); then the kernels checked on the card: the contact solve
#              in one kernel (`fused_kernel.py`: against XLA's iterations on 96 landed robots'
#              problems, two actions of the whole engine in each form, the solve alone at 96
#              robots in XLA's form and the kernel's seven variants; if one other than the
#              default, 64 rows at a time, 8 warps, unrolled, is fastest, set fused.ROW_BLOCK /
#              NUM_WARPS / LOOP_PRODUCT) and the inverses (`cholesky_kernel.py`: the legs'
#              factors by elimination and the attachment block's inverse by sweeps, their errors
#              and the library's, all timed at 96 and 16,384 robots; if a `factor.PER_THREAD`
#              other than 64 is fastest, set it). Each batch size compiles in its own 20-45 s.
# training:    the `paper` preset's episode-at-once loop at 96 and 1,024 envs, 8 rounds each, the
#              learner on the GPU: its steady rate once nothing compiles (`round_s`,
#              `median_round_transitions_per_s`), what the paper's 1M transitions take.
set -u
stages="candidates, elimination, blocks, factors, selection, parts, rid, solve, crossover, profile, flags, attribution, kernels,"
stages="$stages groundtruth, targets or training"
out=${1:?OUTDIR}; stage=${2:?STAGE: $stages}
mkdir -p "$out"
# JAX's persistent compilation cache on the warm machine: a stage after the first loads the
# programs an earlier one compiled (the defaults' step at 96 and 16,384 robots: tens of seconds
# each) instead of compiling them again. `training` reports its compilation, so it runs without.
export JAX_COMPILATION_CACHE_DIR=${JAX_COMPILATION_CACHE_DIR:-/tmp/softcrawl-jax-cache}
nvidia-smi --query-gpu=name,clocks.sm,clocks.mem,memory.total --format=csv | tee -a "$out/log.txt"

# forms NAME LIMIT FLAGS...: the step at 96 and 16,384 robots in each form (one word of
# step_cost.py's flags, each call under LIMIT seconds; "base" instead: BASE's package, labelled),
# every form's robots against the first's on the same robots (--reference: the first's ends in
# /tmp/NAME.npz, 66 MB, not in OUTDIR); the lines also in OUTDIR/NAME.jsonl, and gpu_verdict.py's
# rule on them in OUTDIR/verdict.jsonl (which forms become the default).
forms() {
    local name=$1 limit=$2 flags path
    shift 2
    rm -f "/tmp/$name.npz" "$out/$name.jsonl"
    for flags in "$@"; do
        path=${PYTHONPATH:-}
        if [ "$flags" = base ]; then
            path=${BASE:?BASE: the folder of an earlier commit of softcrawl}:$path
            flags="--label base"
        fi
        PYTHONPATH=$path timeout "$limit" python3 benchmarks/step_cost.py --no-cost --time --batches 96,16384 --calls 3 \
            $flags --reference "/tmp/$name.npz" 2>>"$out/log.txt" | tee -a "$out/targets.jsonl" "$out/$name.jsonl"
    done
    python3 benchmarks/gpu_verdict.py "$out/$name.jsonl" 2>>"$out/log.txt" | sed "s/^{/{\"stage\": \"$name\", /" \
        | tee -a "$out/verdict.jsonl"
}

# the first four candidate forms' flags (the RID kernel, the held solve, the unrolled factor, the
# contact candidates' kernel), with which `candidates` and `elimination` time the fifth
four="--rid-form kernel --resident-rows 128 --unroll-pivots 36 --selection kernel"
case $stage in
candidates)
    timeout 60 python3 -m softcrawl.cli verify --only jax_incline --json 2>>"$out/log.txt" | tee "$out/verify.json"
    forms candidates 130 "" "$four --elimination kernel" "$four" "--rid-form kernel" ;;
elimination)
    forms elimination 130 "$four" "$four --elimination kernel" ;;
parts)
    forms parts 130 "" "--formed-operator"
    timeout 100 python3 benchmarks/fused_kernel.py --batch 96 --batches 96 --actions 2 --calls 5 \
        2>>"$out/log.txt" | tee -a "$out/fused.jsonl" ;;
rid)
    timeout 200 python3 benchmarks/rid_kernel.py --robots 96,16384 --calls 10 2>>"$out/log.txt" \
        | tee -a "$out/rid.jsonl"
    forms rid 130 "--rid-form pairs" "--rid-form kernel" ${BASE:+base} ;;
solve)
    timeout 220 python3 benchmarks/fused_kernel.py --resident-rows 128 --batch 96 --batches 96,16384 --actions 2 \
        --calls 10 2>>"$out/log.txt" | tee -a "$out/fused.jsonl"
    forms solve 130 "" "--resident-rows 128" ;;
selection)
    forms selection 200 "" "--selection kernel" ;;
blocks)
    forms blocks 130 "" base ;;
factors)
    timeout 300 python3 benchmarks/cholesky_kernel.py --robots 96,16384 --calls 5 --sizes 36 \
        2>>"$out/log.txt" | tee -a "$out/cholesky.jsonl" ;;
crossover)
    timeout 420 python3 benchmarks/cholesky_kernel.py --robots 96,1024,2048,4096,16384 --calls 5 \
        2>>"$out/log.txt" | tee -a "$out/cholesky.jsonl" ;;
targets)
    for forms in "dense16 library" "fused16 kernel"; do
        set -- $forms
        timeout 140 python3 benchmarks/step_cost.py --no-cost --time --batches 96,16384 --calls 3 --delassus $1 \
            --cholesky $2 2>>"$out/log.txt" | tee -a "$out/targets.jsonl"
    done
    timeout 130 python3 benchmarks/fused_kernel.py --batch 96 --batches 96 --actions 2 --calls 20 \
        2>>"$out/log.txt" | tee -a "$out/fused.jsonl"
    timeout 180 python3 benchmarks/cholesky_kernel.py --robots 96,16384 --calls 5 2>>"$out/log.txt" \
        | tee -a "$out/cholesky.jsonl" ;;
attribution)
    for forms in "fused16 library" "dense16 kernel"; do
        set -- $forms
        timeout 80 python3 benchmarks/step_cost.py --no-cost --time --batches 96 --calls 5 --delassus $1 --cholesky $2 \
            2>>"$out/log.txt" | tee -a "$out/latency.jsonl"
    done
    timeout 180 python3 benchmarks/fused_kernel.py --batch 96 --batches 16384 --actions 0 --calls 5 \
        2>>"$out/log.txt" | tee -a "$out/fused.jsonl" ;;
kernels)
    timeout 150 python3 benchmarks/step_cost.py --no-cost --time --batches 96,1024 --calls 3 --delassus dense \
        2>>"$out/log.txt" | tee -a "$out/latency.jsonl"
    XLA_FLAGS=--xla_gpu_enable_command_buffer= timeout 90 python3 benchmarks/step_cost.py --no-cost --time \
        --batches 96 --calls 3 --profile /tmp/prof 2>>"$out/log.txt" | tee -a "$out/profile.jsonl"
    gzip -c /tmp/prof/b96/kernels.json > "$out/kernels-b96.json.gz"
    gzip -c /tmp/prof/b96/step.hlo.txt > "$out/step-b96.hlo.txt.gz" ;;
training)  # one call per env count: a call prints its JSON at its end
    for envs in 96 1024; do
        JAX_COMPILATION_CACHE_DIR= timeout 270 python3 benchmarks/train_throughput.py --jax-loops --jax-envs $envs \
            --episodes 8 --preset paper --rollouts episode --set sac.device='"gpu"' 2>>"$out/log.txt" \
            | tee -a "$out/training.jsonl"
    done ;;
profile)
    XLA_FLAGS=--xla_gpu_enable_command_buffer= timeout 560 python3 benchmarks/step_cost.py --no-cost --time \
        --batches 1024,16384 --calls 2 --profile /tmp/prof 2>>"$out/log.txt" | tee -a "$out/profile.jsonl"
    for b in /tmp/prof/b*; do gzip -c "$b/kernels.json" > "$out/kernels-$(basename "$b").json.gz"; done ;;
flags)
    rm -f /tmp/flags.npz
    for flags in "" "--xla_gpu_enable_triton_gemm=false"; do
        XLA_FLAGS="${XLA_FLAGS:-} $flags" timeout 200 python3 benchmarks/step_cost.py --no-cost --time \
            --batches 96,16384 --calls 3 --reference /tmp/flags.npz 2>>"$out/log.txt" \
            | sed "s/^{/{\"xla_flags\": \"$flags\", /" | tee -a "$out/targets.jsonl"
    done ;;
groundtruth)
    timeout 580 python3 benchmarks/groundtruth.py rate --designs 256 --jax-batch 4096 --max-seconds 480 \
        --json "$out/gt-rate.json" 2>>"$out/log.txt" | tail -40 ;;
*)
    echo "unknown stage $stage: $stages" >&2
    exit 2 ;;
esac
