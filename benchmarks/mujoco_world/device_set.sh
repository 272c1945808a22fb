#!/usr/bin/env bash
# Generate MuJoCo validation recordings of a plan and `thinshell diagnose` each one alone, on the GPU
# machine's 16 CPU cores (the `device` tool), in one call: generation takes 1-2 min a recording there
# (10-25 min on the 2-core VM), a diagnosis 0.5-3 min. The recordings are made again on each call (the
# same bytes for the same plan line: MuJoCo 4.0.0 on one thread is deterministic) rather than carried, so
# a call carries code and wheels only.
#
#   benchmarks/mujoco_world/device_set.sh prepare      # here, with network: .device_mj/wheels (MuJoCo
#       4.0.0 and what `import mujoco` loads, cp312) and .device_mj/scene.yaml (the scene of
#       ../shared/data/reference_bags/nominal_s101, which the device does not carry); needs .device_cpu
#       prepared by `benchmarks/device_cpu.sh prepare diagnose` (Taichi, rosbags; add the ruptures wheel)
#   run(command="bash .device_cpu/src/benchmarks/mujoco_world/device_set.sh run 'dev|blind'",
#       carry=[".device_mj", ".device_cpu/src", ".device_cpu/wheels"])
#       on the device, from the checkout's root: SETS (a regex over the plan's first column; default dev),
#       PLAN (default benchmarks/mujoco_world/plans/session37.txt, relative to .device_cpu/src). Back under
#       $OUT: md5.txt of the recordings, and device_cpu.sh's machine.txt, results.jsonl (one summary line a
#       recording), summary.txt, logs.tar.gz; with KEEP_BAGS=1 also the recordings. JOBS (16)
#       and JOB_TIMEOUT (330 s) as in device_cpu.sh; DIAG_ARGS: more `thinshell diagnose` arguments (e.g. --drive).
set -u
mode=${1:-}
R=$(pwd)
if [ "$mode" = prepare ]; then
    mkdir -p "$R/.device_mj/wheels"
    "${PYTHON:-$R/.venv/bin/python}" -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 \
        --implementation cp --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 \
        --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 -d "$R/.device_mj/wheels" \
        mujoco==4.0.0 mujoco-core==4.0.0 glfw==2.11.0 pyopengl==3.1.10 || exit 1
    cp "${SCENE:-$R/../shared/data/reference_bags/nominal_s101/scene.yaml}" "$R/.device_mj/scene.yaml" || exit 1
    du -sh "$R/.device_mj"
    exit 0
fi
[ "$mode" = run ] || { echo "usage: $0 prepare | run [SETS] [PLAN]" >&2; exit 2; }
SRC=$R/.device_cpu/src
SETS=${2:-dev}
PLAN=$SRC/${3:-benchmarks/mujoco_world/plans/session37.txt}
SCENE=$R/.device_mj/scene.yaml
# MuJoCo's wheels and device_cpu.sh's (rosbags and its needs: the generator writes the bags)
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site \
    "$R"/.device_mj/wheels/*.whl "$R"/.device_cpu/wheels/*.whl || exit 1
rm -rf /tmp/gen /tmp/dc
mkdir -p /tmp/gen/logs /tmp/dc
gen() {  # gen SET NAME VARIANT MAGNITUDE MOTION SEED [DIRECTION]
    local set=$1 name=$2 var=$3 mag=$4 mot=$5 seed=$6 dir=${7:-}
    local args=(--scene "$SCENE" --variant "$var" --motion "$mot" --seed "$seed")
    [ "$mag" = - ] || args+=(--magnitude "$mag")
    [ -z "$dir" ] || args+=("--direction=$dir")
    mkdir -p "/tmp/gen/logs/$name"
    (cd "/tmp/gen/logs/$name" && PYTHONPATH=/tmp/site:$SRC OMP_NUM_THREADS=1 MUJOCO_GL=disable \
        timeout 300 python3 -m benchmarks.mujoco_world.generate "/tmp/gen/$set/$name" "${args[@]}" > out.log 2>&1
     rc=$?; echo "$name generate exit $rc" >> /tmp/gen/status.txt
     [ $rc = 0 ] || tail -5 out.log) &
}
while read -r line; do gen $line; done < <(grep -v '^#' "$PLAN" | grep -E "^($SETS) ")
wait
cat /tmp/gen/status.txt
(cd /tmp/gen && md5sum ./*/*_s*/*.mcap) > "$OUT/md5.txt"
# KEEP_BAGS=1: the recordings come back too, as bags.tgz.part_aa, _ab, ... (15 MB each; about 2.5 MB a
# recording; `cat bags.tgz.part_* | tar -xz` here); DIAGNOSE=0: generate only
if [ "${KEEP_BAGS:-0}" = 1 ]; then
    (cd /tmp/gen && tar -czf - --exclude=./logs --exclude=./status.txt .) | split -b 15M - "$OUT/bags.tgz.part_"
fi
[ "${DIAGNOSE:-1}" = 0 ] && exit 0
ln -s "$SRC" /tmp/dc/src
ln -s "$R/.device_cpu/wheels" /tmp/dc/wheels
ln -s /tmp/gen /tmp/dc/data
for b in $(cd /tmp/gen && ls -d ./*/*_s*/ | grep -v '^./logs/' | sort); do
    n=$(basename "$b")
    diag="python -m thinshell_ros.cli diagnose \$DATA/${b#./} ${DIAG_ARGS:-} --json /tmp/a_$n.json --force"
    echo "$diag; python $SRC/benchmarks/diagnose_summary.py $n alone /tmp/a_$n.json"
done > /tmp/dc/jobs.txt
JOBS=${JOBS:-16} JOB_TIMEOUT=${JOB_TIMEOUT:-330} bash "$SRC/benchmarks/device_cpu.sh" run /tmp/dc
