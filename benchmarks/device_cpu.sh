#!/usr/bin/env bash
# Run CPU-bound thinshell commands in parallel on the GPU machine's CPU cores (the `device` tool).
#
# The GPU machine (nvidia-h100-x1 / nvidia-h200: 16 CPU cores, Python 3.12 with NumPy, SciPy, PyYAML,
# matplotlib, tqdm; no Taichi, no MKL, no network) copies the working tree of the checkout the session
# started in, not a helper's worktree. This script therefore packs what a run needs into one folder,
# DIR (default: .device_cpu/ in that checkout, ignored by git), which the device call carries:
#
#   DIR/src/      a copy of THIS checkout's code (no .git, tests, docs, bags)
#   DIR/wheels/   cp312 manylinux wheels of the packages the machine lacks, by profile:
#                   taichi       the Taichi 1.7.4 wheel (54 MiB) and dill (imported by taichi)
#                   taichi-slim  Taichi without its C API library, examples and C headers, as an xz
#                                tarball (24 MiB), and dill: the same kernels (`import taichi` and
#                                ti.init do not load libtaichi_c_api.so)
#                   cma          cma 4.5.0 (thinshell optimise's CMA-ES)
#                   rosbags      rosbags 0.11.9 and its needs (apsw, backports.zstd, lz4, ruamel.yaml,
#                                typing_extensions)
#                   bags         the reference bags, copied to DIR/data/reference_bags
#                   optimise     = taichi cma      (thinshell optimise / bench optimise)
#                   diagnose     = taichi-slim rosbags bags  (python -m benchmarks.diagnose_bench --labelled, whose
#                                replays run on Taichi CPU)
#   DIR/jobs.txt  the commands, one a line (written by the caller, kept by `prepare`; see below)
#
# The device tool carries at most 64 MiB: DIR plus the device checkout's tracked files (about 5 MiB).
# `prepare` prints both and refuses a total over the limit: optimise 62 MiB, diagnose 58 MiB (with
# the full Taichi wheel it would be 89 MiB: it does not fit). taichi-slim's xz takes about 5 min here.
#
#   benchmarks/device_cpu.sh prepare PROFILE [PROFILE ...]      # here, with network
#       environment: DIR (default /work/main/.device_cpu), DEVICE_CHECKOUT (default /work/main: the tree the
#       device copies, whose tracked files count towards the limit), BAGS (default
#       /work/shared/data/reference_bags), PYTHON (default /work/main/.venv/bin/python).
#   benchmarks/device_cpu.sh run [DIR]                          # on the device, from the checkout's root
#       installs DIR/wheels (*.whl, *.tar.xz) into /tmp/site, then runs every line of DIR/jobs.txt (blank and # lines
#       skipped) as `bash -c LINE` from DIR/src, JOBS at a time (default: the machine's cores), each
#       with one thread for BLAS, OpenMP and Taichi (TI_CPU_MAX_NUM_THREADS=1), stopped after
#       JOB_TIMEOUT s (default 560). `python` in a line is the machine's python3, `$DATA` is DIR/data.
#       Back under $OUT (at most 8 files come back): machine.txt (CPU, cores, versions),
#       results.jsonl (every line of a job's stdout that starts with '{', as {"job": N, "row": ...}),
#       summary.txt (per job, tab-separated: number, exit status, wall seconds, the command) and logs.tar.gz (each job's
#       stdout and stderr).
#
# A device call (command at most 2000 characters; the machine is released 30 s after a call):
#   run(command="bash .device_cpu/src/benchmarks/device_cpu.sh run .device_cpu", carry=[".device_cpu"],
#       timeout_s=600)
# Lines of jobs.txt, e.g.
#   python -m thinshell_ros.cli bench optimise --tasks forming --methods cma --seeds 1 --first-seed 1 --episodes 60 --population 8 --max-time 400 --json
#   python -m benchmarks.diagnose_bench --labelled $DATA/reference_bags --json
# Put the longest jobs first: they start first.
set -u
mode=${1:-}

if [ "$mode" = prepare ]; then
    shift
    [ $# -ge 1 ] || { echo "usage: $0 prepare optimise|diagnose [...]" >&2; exit 2; }
    src=$(cd "$(dirname "$0")/.." && pwd)
    dir=${DIR:-/work/main/.device_cpu}
    checkout=${DEVICE_CHECKOUT:-/work/main}
    PY=${PYTHON:-/work/main/.venv/bin/python}
    rm -rf "$dir/src" "$dir/wheels" "$dir/data"
    mkdir -p "$dir/src" "$dir/wheels"
    # the checkout's files that git tracks or would track (not its ignored venv, build outputs, caches)
    (cd "$src" && git ls-files -co --exclude-standard -z -- . ':!:tests' ':!:docs' ':!:bags' \
        | tar --null -T - -cf -) | (cd "$dir/src" && tar -xf -) || exit 1
    pkgs=()
    slim=0
    for profile in "$@"; do
        case $profile in
            optimise) set -- "$@" taichi cma ;;
            diagnose) set -- "$@" taichi-slim rosbags bags ;;
        esac
    done
    for profile in "$@"; do
        case $profile in
            optimise|diagnose) ;;
            taichi) pkgs+=(taichi==1.7.4 dill==0.4.1) ;;
            taichi-slim) pkgs+=(dill==0.4.1); slim=1 ;;
            cma) pkgs+=(cma==4.5.0) ;;
            rosbags) pkgs+=(rosbags==0.11.9 apsw==3.54.1.0 backports.zstd==1.8.0 lz4==4.4.5 ruamel.yaml==0.19.1
                            typing_extensions==4.16.0) ;;
            bags) mkdir -p "$dir/data"
                  cp -r "${BAGS:-/work/shared/data/reference_bags}" "$dir/data/reference_bags" || exit 1 ;;
            *) echo "unknown profile $profile (optimise, diagnose, taichi, taichi-slim, cma, rosbags, bags)" >&2
               exit 2 ;;
        esac
    done
    mapfile -t pkgs < <(printf '%s\n' "${pkgs[@]}" | sort -u)
    if [ "$slim" = 1 ] && printf '%s\n' "${pkgs[@]}" | grep -q '^taichi=='; then
        echo "taichi and taichi-slim exclude each other" >&2
        exit 2
    fi
    download() {
        "$PY" -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
            --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 --platform manylinux_2_17_x86_64 \
            --platform manylinux2014_x86_64 --platform manylinux1_x86_64 -d "$@"
    }
    [ ${#pkgs[@]} -eq 0 ] || download "$dir/wheels" "${pkgs[@]}" || exit 1
    if [ "$slim" = 1 ]; then
        # Taichi without its C API library (libtaichi_c_api.so, for C/AOT users; `import taichi` and
        # the kernels do not load it), examples and C headers, packed with xz: 24 MiB instead of the
        # wheel's 54 MiB. Unpacked into /tmp/site by `run`.
        tmp=$(mktemp -d)
        download "$tmp" taichi==1.7.4 || exit 1
        (cd "$tmp" && unzip -q taichi-*.whl && rm -rf taichi/_lib/c_api taichi/examples taichi-*.data taichi-*.whl \
            && tar -cf - taichi taichi-*.dist-info | xz -T2 -6 > "$dir/wheels/taichi-slim.tar.xz") || exit 1
        rm -rf "$tmp"
    fi
    tracked=$(cd "$checkout" && git ls-files -z | xargs -0 du -cb 2>/dev/null | tail -1 | cut -f1)
    carried=$(du -sb "$dir" | cut -f1)
    total=$((tracked + carried))
    echo "carried $dir: $((carried / 1048576)) MiB; tracked files of $checkout: $((tracked / 1048576)) MiB;" \
         "total $((total / 1048576)) MiB of 64 MiB"
    ls -la "$dir/wheels"
    if [ "$total" -gt $((64 * 1048576)) ]; then
        echo "over the device tool's 64 MiB: carry fewer profiles" >&2
        exit 1
    fi
    exit 0
fi
if [ "$mode" != run ]; then
    echo "usage: $0 prepare PROFILE... | run [DIR]" >&2
    exit 2
fi

dir=$(cd "${2:-.device_cpu}" && pwd) || exit 1
out=${OUT:-/tmp/device_cpu_out}
mkdir -p "$out"
if ls "$dir"/wheels/*.whl > /dev/null 2>&1; then
    python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site \
        "$dir"/wheels/*.whl || exit 1
fi
mkdir -p /tmp/site
for t in "$dir"/wheels/*.tar.xz; do
    [ -e "$t" ] && { tar -xJf "$t" -C /tmp/site || exit 1; }
done
cores=$(getconf _NPROCESSORS_ONLN)  # before OMP_NUM_THREADS=1, which GNU nproc would report
export PYTHONPATH=/tmp/site:$dir/src PYTHONUNBUFFERED=1 DATA=$dir/data
export OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 MKL_NUM_THREADS=1 TI_CPU_MAX_NUM_THREADS=1
# `python` in a job line is the machine's python3 (the one with NumPy and SciPy; a function, not a
# link: a link to a virtual environment's interpreter loses the environment)
PY=$(command -v python3)
python() { "$PY" "$@"; }
export PY
export -f python
{
    grep -m1 'model name' /proc/cpuinfo | sed 's/.*: /cpu: /'
    echo "cores: $cores (affinity: $(nproc --all 2>/dev/null) / $(taskset -pc $$ 2>/dev/null | sed 's/.*: //'))"
    free -g | awk '/Mem:/ {print "memory (GiB): " $2}'
    python -c "import sys, numpy, scipy; print('python', sys.version.split()[0], sys.executable, 'numpy', numpy.__version__, 'scipy', scipy.__version__)"
    python -c "import taichi; print('taichi', taichi.__version__)" 2>/dev/null | grep -v '^\[Taichi\]'
    date -u +"start %Y-%m-%dT%H:%M:%SZ"
} | tee "$out/machine.txt"
jobs_file=$dir/jobs.txt
[ -f "$jobs_file" ] || { echo "no $jobs_file" >&2; exit 2; }
logs=/tmp/device_cpu_logs
rm -rf "$logs"
mkdir -p "$logs"
JOBS=${JOBS:-$cores}
JOB_TIMEOUT=${JOB_TIMEOUT:-560}
echo "jobs: $(grep -cv '^\s*\(#\|$\)' "$jobs_file"), $JOBS at a time, each at most $JOB_TIMEOUT s" | tee -a "$out/machine.txt"

one_job() {  # one_job N LINE: run LINE from DIR/src, logs and status under $logs
    local n=$1 line=$2 t0 rc
    t0=$(date +%s)
    (cd "$dir/src" && timeout "$JOB_TIMEOUT" bash -c "$line") > "$logs/$n.out" 2> "$logs/$n.err"
    rc=$?
    printf '%s\t%s\t%s\t%s\n' "$n" "$rc" "$(($(date +%s) - t0))" "$line" > "$logs/$n.status"
    echo "job $n: exit $rc"
}
n=0
while IFS= read -r line; do
    case $line in ''|'#'*) continue ;; esac
    n=$((n + 1))
    while [ "$(jobs -rp | wc -l)" -ge "$JOBS" ]; do wait -n; done
    one_job "$n" "$line" &
done < "$jobs_file"
wait
: > "$out/results.jsonl"
for s in $(ls "$logs"/*.status | sort -V); do
    k=$(basename "$s" .status)
    cat "$s" >> "$out/summary.txt"
    grep '^{' "$logs/$k.out" | while IFS= read -r row; do
        printf '{"job": %s, "row": %s}\n' "$k" "$row"
    done >> "$out/results.jsonl"
done
tar -czf "$out/logs.tar.gz" -C "$logs" .
date -u +"end %Y-%m-%dT%H:%M:%SZ" | tee -a "$out/machine.txt"
cat "$out/summary.txt"
