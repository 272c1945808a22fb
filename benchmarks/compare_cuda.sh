#!/usr/bin/env bash
# Compare two checkouts' lockstep batches on the GPU machine in one call (same machine, same warm state):
#
#   benchmarks/compare_cuda.sh WHEELS NAME=DIR [NAME=DIR ...]
#
# run from anywhere on the GPU machine: installs the carried wheels (benchmarks/device_cuda.sh prepare)
# into /tmp/site (once a machine), then for each DIR (a checkout: the device tool's copy of the repository root, or a
# branch's copy made by benchmarks/sync_gpu_src.sh) runs, from that DIR with that DIR first on the path,
#   bench      thinshell bench batch --lockstep --arch cuda --scene $SCENE --sizes $SIZES --steps $STEPS --json
#   profile    python3 benchmarks/profile_lockstep.py --arch cuda --B $PROFILE_B --steps $PROFILE_STEPS
# (PARTS="bench profile" by default; SCENE forming, SIZES "256", STEPS 5, PROFILE_B 256, PROFILE_STEPS 3, PART_TIMEOUT
# 170 s per process). The JSON lines go to $OUT/NAME_bench.jsonl, the profiles' tails (last 90 lines) to
# $OUT/NAME_profile.txt ($OUT: the device tool's folder, else /tmp/compare_cuda_out). The first process
# compiles Taichi's kernels into the offline cache, which later processes share for unchanged kernels:
# `thinshell bench batch` reports that compilation apart (jit_s) and times only the steps.
set -u
wheels=$1; shift
out=${OUT:-/tmp/compare_cuda_out}
mkdir -p "$out"
[ -d /tmp/site/taichi ] || python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
    --target /tmp/site "$wheels"/*.whl || exit 1
export PYTHONUNBUFFERED=1
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader
date -u
for part in ${PARTS:-bench profile}; do
    for spec in "$@"; do
        name=${spec%%=*}
        dir=$(cd "${spec#*=}" && pwd)  # absolute: the parts run from DIR with DIR on PYTHONPATH
        echo "=== $name $part ($dir, $(cd "$dir" && git rev-parse --short HEAD 2>/dev/null || echo copy))"
        case $part in
            bench)
                (cd "$dir" && PYTHONPATH=/tmp/site:$dir timeout "${PART_TIMEOUT:-170}" python3 -m thinshell_ros.cli bench batch \
                    --lockstep --arch cuda --scene "${SCENE:-forming}" --sizes ${SIZES:-256} --steps "${STEPS:-5}" --json 2>/dev/null) \
                    | grep '^{' | tee -a "$out/${name}_bench.jsonl" ;;
            profile)
                (cd "$dir" && PYTHONPATH=/tmp/site:$dir timeout "${PART_TIMEOUT:-170}" python3 benchmarks/profile_lockstep.py \
                    --arch cuda --B "${PROFILE_B:-256}" --steps "${PROFILE_STEPS:-3}" 2>&1) \
                    | grep -v '^\[Taichi\]' | grep -v Warning | tail -90 | tee "$out/${name}_profile.txt" ;;
            *) echo "unknown part $part" >&2; exit 2 ;;
        esac
    done
done
