#!/usr/bin/env bash
# Prepare the GPU machine and run the GPU benchmarks of docs/benchmarks.md.
#
# The GPU machine (the `device` tool's nvidia-h100-x1 / nvidia-h200) has Python 3.12, NumPy, SciPy
# and PyYAML but no Taichi, and no network. Its Python packages therefore travel as wheels:
#
#   benchmarks/device_cuda.sh prepare [WHEELS]   # here, with network: download the cp312 wheels
#                                                # (Taichi, the two packages `import taichi` loads:
#                                                # colorama, dill, and cma for `thinshell optimise`)
#                                                # into WHEELS (default .gpu_wheels/, ignored by git;
#                                                # 56.8 MB, so that the carried total of
#                                                # the device tool, 64 MiB, also holds the repository;
#                                                # the tracked tree is ~10 MB in 4 KiB blocks, so the
#                                                # whole folder no longer fits beside it: carry a folder
#                                                # of the Taichi, dill and colorama wheels alone (56.4 MB)
#                                                # unless a part runs `thinshell optimise`)
#   benchmarks/device_cuda.sh run [WHEELS]       # on the GPU machine, from the repository root,
#                                                # with WHEELS carried: install them into /tmp/site,
#                                                # then run the benchmarks below
#
# A helper's branch whose checkout is not the one the device tool copies travels as a copy of its code
# (benchmarks/sync_gpu_src.sh DEST, DEST ignored by git and carried beside WHEELS); the command then
# runs this script from DEST. Where that copy, the wheels and the tree exceed the tool's 64 MiB, carry only
# the branch's changed files (`git diff --name-only BASE`, new files too) in DEST and lay them over a copy of
# the device's tree: `mkdir /tmp/br && tar --exclude=./.gpu_wheels --exclude=./DEST -cf - . | tar -xf - -C /tmp/br
# && cp -r DEST/. /tmp/br/`, then run from /tmp/br with the repository root's run as the baseline (session 38).
#
# `profile` (PROFILE_SIZES, default "64 256"; STEPS) runs benchmarks/profile_lockstep.py on CUDA: the
# wall time of a lockstep Forming step split into the solver's parts (one step first for compilation
# and set-up, then STEPS timed), and benchmarks/parts_lockstep.py --B 256 (each term's gradient,
# energy and Hessian, the projected elastic Hessian, the CG's operator, set-up and solve, in ms).
#
# What `run` measures (one process per arch: Taichi initialises one arch per process), each line of
# JSON also appended to $OUT/bench.jsonl when $OUT is set (the device tool returns that folder); the
# parts named in $PARTS (default: all, in this order):
#   lockstep_cuda_forming  thinshell bench batch --lockstep --arch cuda --scene forming --sizes $LOCK_SIZES
#   lockstep_cuda_task     thinshell bench batch --lockstep --arch cuda --scene $TASK   --sizes $LOCK_TASK_SIZES
#   lockstep_cpu_forming   thinshell bench batch --lockstep --arch cpu  --scene forming --sizes $LOCK_CPU_SIZES
#   lockstep_cpu_task      thinshell bench batch --lockstep --arch cpu  --scene $TASK   --sizes $LOCK_CPU_SIZES
#   batch_cuda_forming     thinshell bench batch --arch cuda --scene forming  --sizes $CUDA_SIZES  (one copy after another)
#   batch_cpu_forming      thinshell bench batch --arch cpu  --scene forming  --sizes $CPU_SIZES
#   batch_cuda_task        thinshell bench batch --arch cuda --scene $TASK    --sizes $TASK_SIZES
#   batch_cpu_task         thinshell bench batch --arch cpu  --scene $TASK    --sizes $TASK_SIZES
#   forming                thinshell bench forming --arch A --json --repeat $FORMING_REPEAT for A in $FORMING_ARCHS
#                          (single-environment figures; FORMING_ARCHS default "cuda cpu numpy", FORMING_REPEAT 1)
#   single_profile         benchmarks/profile_single.py --arch A for A in $FORMING_ARCHS but numpy (where a
#                          single environment's step goes: kernel launches, transfers, linear solve, the rest;
#                          with --kernel-profiler on cuda unless KERNEL_PROFILER=0; PROFILE_SINGLE_ARGS adds options,
#                          e.g. "--phases --launch-costs": the parts side by side, a launch's host time by its parts)
#   single_compare         the `forming` bench of the baseline tree BASELINE_ROOT (e.g. the device's copy of main)
#                          and of this tree, alternated, for A in $FORMING_ARCHS, SINGLE_ROUNDS times (default 1),
#                          --repeat $FORMING_REPEAT (default 3 here): same machine, same call
#   single_rounds          benchmarks/single_rounds.py: one worker process per tree (BASELINE_ROOT as "baseline" when
#                          set, then this tree) and arch of $FORMING_ARCHS (default "cuda cpu"), the Forming
#                          trajectory $FORMING_REPEAT times (default 3) per worker a round, SINGLE_ROUNDS rounds
#                          (default 5) with the workers' order turned each round; medians, ranges, the per-round
#                          cuda / cpu ratio (the figure of record for "no slower"); every run in
#                          $out/single_rounds.jsonl
#                          (about 4 x 10 s of start-up, then 2-3 s a run on an H100: PART_TIMEOUT=400 for the defaults)
#   optimise_cuda          thinshell optimise $TASK --method cma --batched --backend B --episodes $OPT_EPISODES
#                          (default 40: one CMA-ES generation of the task's population, every rollout of it
#                          stepped together) --seed $OPT_SEED (0) for B in $OPT_BACKENDS (default taichi-cuda):
#                          the wall time of optimising one task with a batched population (needs the cma wheel
#                          in WHEELS)
#   kernel_tests           THINSHELL_TEST_ARCH=cuda pytest $KERNEL_TESTS (default: the launch, transfer, fused elastic,
#                          device-copy, band-block, per-copy vector, device-gradient, displacement-bound, per-copy
#                          energy, compaction, sorted-pair, batched CG and CG operator kernel tests, the projection of
#                          listed blocks by kernels (Jacobi and host LAPACK; the spring membrane's; the fused parts'
#                          blocks of listed elements; the Jacobi kernel against LAPACK; the contact pair blocks of
#                          marked copies left on the device) and the contact
#                          pair batch's packed launch; a file missing from the tree is an error)
# each batch part with --steps $STEPS. Environment overrides: PARTS, STEPS (10), LOCK_SIZES ("1 16 64 256 1024"),
# LOCK_TASK_SIZES ("1 16 64 256"), LOCK_CPU_SIZES ("1 16 64"), CUDA_SIZES ("1 2 4 8 16 32"), CPU_SIZES
# ("1 4 16"), TASK (folding_u), TASK_SIZES ("1 4 16"), PART_TIMEOUT (seconds per benchmark, 170; a
# batch benchmark prints each size as it finishes, so a part stopped at its limit keeps its smaller
# sizes), PYTHON (the interpreter, default python3). The GPU machine has no MKL: its direct solves
# are SciPy's (a lockstep batch on CUDA solves with the batched CG on the device).
set -u
mode=${1:-run}
wheels=${2:-.gpu_wheels}
PY=${PYTHON:-python3}

if [ "$mode" = prepare ]; then
    mkdir -p "$wheels"
    "$PY" -m pip download --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
        --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 --platform manylinux_2_17_x86_64 \
        --platform manylinux2014_x86_64 -d "$wheels" \
        taichi==1.7.4 colorama==0.4.6 dill==0.4.1 cma==4.5.0 || exit 1
    du -sh "$wheels"
    exit 0
fi
if [ "$mode" != run ] && [ "$mode" != profile ]; then
    echo "usage: $0 prepare|run|profile [WHEELS]" >&2
    exit 2
fi

if [ -d /tmp/site/taichi ]; then
    echo "wheels already installed in /tmp/site"
elif ls "$wheels"/*.whl > /dev/null 2>&1; then
    "$PY" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site "$wheels"/*.whl || exit 1
else
    echo "no wheels in $wheels: using the interpreter's own packages"
fi
export PYTHONPATH=/tmp/site:$PWD PYTHONUNBUFFERED=1
out=${OUT:-/tmp/device_cuda_out}
mkdir -p "$out"
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader | tee "$out/machine.txt"
nproc | sed 's/^/cpu cores: /' | tee -a "$out/machine.txt"
"$PY" -c "import sys, numpy, scipy, taichi; print('python', sys.version.split()[0], 'numpy', numpy.__version__, 'scipy', scipy.__version__, 'taichi', taichi.__version__)" 2>&1 | grep -v '^\[Taichi\]' | tee -a "$out/machine.txt"

STEPS=${STEPS:-10}
if [ "$mode" = profile ]; then
    for B in ${PROFILE_SIZES:-64 256}; do
        echo "=== profile B=$B"
        timeout "${PART_TIMEOUT:-170}" "$PY" benchmarks/profile_lockstep.py --arch cuda --B "$B" --steps "$STEPS" \
            > "$out/profile_$B.out" 2>&1
        echo "exit $?"
        grep -v '^\[Taichi\]' "$out/profile_$B.out" | grep -v Warning | tail -40
    done
    timeout "${PART_TIMEOUT:-170}" "$PY" benchmarks/parts_lockstep.py --arch cuda --B 256 > "$out/parts_256.out" 2>&1
    echo "=== parts B=256: exit $?"
    grep ' ms$' "$out/parts_256.out"
    exit 0
fi
PART_TIMEOUT=${PART_TIMEOUT:-170}
TASK=${TASK:-folding_u}
KT=tests/sim_core/ti_kernels
KERNEL_TESTS=${KERNEL_TESTS:-$KT/test_launch.py $KT/test_transfer.py $KT/test_fused_elastic.py $KT/test_device_copy.py \
$KT/test_band_cholesky.py $KT/test_copy_vectors.py $KT/test_device_gradient.py $KT/test_displacement_bounds.py \
$KT/test_copy_energies.py $KT/test_compaction.py $KT/test_sorted_pairs.py $KT/test_pcg.py $KT/test_device_operator.py \
$KT/test_block_projection.py::test_projection_of_listed_blocks_by_kernels_adds_what_the_host_projection_adds \
$KT/test_block_projection.py::test_spring_membrane_projection_by_kernels_adds_what_the_host_path_adds \
$KT/test_block_projection.py::test_the_blocks_of_listed_elements_are_the_whole_evaluations_to_the_bit \
$KT/test_jacobi_projection.py $KT/test_householder_projection.py $KT/test_backtrack.py $KT/test_projected_subset.py \
$KT/test_contact_batch.py::test_packed_launches_equal_the_default_ones_bit_for_bit}
bench() {  # bench NAME ARGS...: one benchmark process, its JSON lines kept
    local name=$1; shift
    echo "=== $name: thinshell bench $*"
    timeout "$PART_TIMEOUT" "$PY" -m thinshell_ros.cli bench "$@" > "$out/$name.out" 2> "$out/$name.err"
    echo "exit $?"
    grep '^{' "$out/$name.out" | tee -a "$out/bench.jsonl"
    grep -v '^\[Taichi\]' "$out/$name.err" | tail -3
}
PARTS=${PARTS:-lockstep_cuda_forming lockstep_cuda_task lockstep_cpu_forming lockstep_cpu_task batch_cuda_forming batch_cpu_forming batch_cuda_task batch_cpu_task forming}
for part in $PARTS; do
    case $part in
        lockstep_cuda_forming) bench "$part" batch --lockstep --arch cuda --scene forming --sizes ${LOCK_SIZES:-1 16 64 256 1024} --steps "$STEPS" --json ;;
        lockstep_cuda_task) bench "$part" batch --lockstep --arch cuda --scene "$TASK" --sizes ${LOCK_TASK_SIZES:-1 16 64 256} --steps "$STEPS" --json ;;
        lockstep_cpu_forming) bench "$part" batch --lockstep --arch cpu --scene forming --sizes ${LOCK_CPU_SIZES:-1 16 64} --steps "$STEPS" --json ;;
        lockstep_cpu_task) bench "$part" batch --lockstep --arch cpu --scene "$TASK" --sizes ${LOCK_CPU_SIZES:-1 16 64} --steps "$STEPS" --json ;;
        batch_cuda_forming) bench "$part" batch --arch cuda --scene forming --sizes ${CUDA_SIZES:-1 2 4 8 16 32} --steps "$STEPS" --json ;;
        batch_cpu_forming) bench "$part" batch --arch cpu --scene forming --sizes ${CPU_SIZES:-1 4 16} --steps "$STEPS" --json ;;
        batch_cuda_task) bench "$part" batch --arch cuda --scene "$TASK" --sizes ${TASK_SIZES:-1 4 16} --steps "$STEPS" --json ;;
        batch_cpu_task) bench "$part" batch --arch cpu --scene "$TASK" --sizes ${TASK_SIZES:-1 4 16} --steps "$STEPS" --json ;;
        forming) for arch in ${FORMING_ARCHS:-cuda cpu numpy}; do
                bench "forming_$arch" forming --arch "$arch" --repeat "${FORMING_REPEAT:-1}" --json
            done ;;
        single_profile) for arch in ${FORMING_ARCHS:-cuda cpu}; do
                [ "$arch" = numpy ] && continue
                flag=; [ "$arch" = cuda ] && [ "${KERNEL_PROFILER:-1}" = 1 ] && flag=--kernel-profiler
                echo "=== single_profile $arch"
                timeout "$PART_TIMEOUT" "$PY" benchmarks/profile_single.py --arch "$arch" $flag \
                    ${PROFILE_SINGLE_ARGS:-} > "$out/profile_single_$arch.out" 2>&1
                echo "exit $?"
                grep -v '^\[Taichi\]' "$out/profile_single_$arch.out" | grep -v Warning | head -120
            done ;;
        single_compare) [ -n "${BASELINE_ROOT:-}" ] || { echo "single_compare needs BASELINE_ROOT" >&2; exit 2; }
            for round in $(seq "${SINGLE_ROUNDS:-1}"); do
                for arch in ${FORMING_ARCHS:-cuda cpu}; do
                    for label in baseline branch; do
                        tree=$PWD; [ "$label" = baseline ] && tree=$BASELINE_ROOT
                        echo "=== single_compare round $round $arch $label ($tree)"
                        (cd "$tree" && PYTHONPATH=/tmp/site:$tree timeout "$PART_TIMEOUT" "$PY" -m thinshell_ros.cli \
                            bench forming --arch "$arch" --repeat "${FORMING_REPEAT:-3}" --json) \
                            > "$out/compare_${round}_${arch}_$label.out" 2>&1
                        echo "exit $?"
                        grep '^{' "$out/compare_${round}_${arch}_$label.out" \
                            | sed "s/^{/{\"code\": \"$label\", \"round\": $round, /" | tee -a "$out/bench.jsonl"
                    done
                done
            done ;;
        single_rounds) trees="this=."; [ -n "${BASELINE_ROOT:-}" ] && trees="baseline=$BASELINE_ROOT $trees"
            echo "=== single_rounds: $trees, archs ${FORMING_ARCHS:-cuda cpu}"
            timeout "$PART_TIMEOUT" "$PY" benchmarks/single_rounds.py --trees $trees \
                --archs ${FORMING_ARCHS:-cuda cpu} --rounds "${SINGLE_ROUNDS:-5}" --repeat "${FORMING_REPEAT:-3}" \
                --site /tmp/site --out "$out/single_rounds.jsonl" > "$out/single_rounds.out" 2>&1
            echo "exit $?"
            grep -v '^{' "$out/single_rounds.out" | grep -v '^\[Taichi\]' | tail -30 ;;
        optimise_cuda) for backend in ${OPT_BACKENDS:-taichi-cuda}; do
                echo "=== optimise_cuda: thinshell optimise $TASK --method cma --batched --backend $backend"
                timeout "$PART_TIMEOUT" "$PY" -m thinshell_ros.cli optimise "$TASK" --method cma --batched \
                    --backend "$backend" --episodes "${OPT_EPISODES:-40}" --seed "${OPT_SEED:-0}" \
                    --out "$out/optimise_$backend" --no-progress > "$out/optimise_$backend.out" 2>&1
                echo "exit $?"
                tail -2 "$out/optimise_$backend.out"
                "$PY" -c "import json, sys; r = json.load(open(sys.argv[1])); print(json.dumps({k: r.get(k) for k in (
                    'task', 'backend', 'episodes', 'horizon', 'wall_time_s', 'rollouts_per_s', 'best_score',
                    'success_score', 'stop_reason')}))" "$out/optimise_$backend/result.json" | tee -a "$out/bench.jsonl"
            done ;;
        kernel_tests) echo "=== kernel_tests (THINSHELL_TEST_ARCH=cuda): $KERNEL_TESTS"
            THINSHELL_TEST_ARCH=cuda timeout "$PART_TIMEOUT" "$PY" -m pytest -q -rf -p no:cacheprovider $KERNEL_TESTS \
                > "$out/kernel_tests.out" 2>&1
            echo "exit $?"
            grep -E '^(FAILED|ERROR)|passed|failed' "$out/kernel_tests.out" | tail -20 ;;
        *) echo "unknown part $part" >&2; exit 2 ;;
    esac
done
