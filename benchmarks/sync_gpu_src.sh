#!/usr/bin/env bash
# Copy this checkout's code (no .git, docs, bags; of the tests only the Taichi kernel tests and their
# support, which run on CUDA with THINSHELL_TEST_ARCH=cuda) into DEST (default ../main/.gpu_src), the folder
# the `device` tool carries to the GPU machine when the device copies another checkout's working tree.
#
#   benchmarks/sync_gpu_src.sh DEST          # the whole code (about 3.5 MB)
#   benchmarks/sync_gpu_src.sh DEST BASE     # only the files changed since the commit BASE (new files too),
#                                            # to lay over a copy of the device's tree at BASE (where the
#                                            # whole code, the wheels and the device's tree exceed 64 MiB):
#                                            # mkdir /tmp/br && tar --exclude=./.gpu_wheels --exclude=./DEST -cf - .
#                                            # | tar -xf - -C /tmp/br && cp -r DEST/. /tmp/br/
set -eu
src=$(cd "$(dirname "$0")/.." && pwd)
dest=${1:-/work/main/.gpu_src}
base=${2:-}
rm -rf "$dest"
mkdir -p "$dest"
if [ -n "$base" ]; then
    (cd "$src" && { git diff --name-only -z "$base" --diff-filter=ACMR -- .; git ls-files -oz --exclude-standard; } \
        | tar --null -T - -cf -) | (cd "$dest" && tar -xf -)
    du -sb "$dest"
    exit 0
fi
# the checkout's files that git tracks or would track (not its ignored venv, build outputs, caches)
(cd "$src" && git ls-files -co --exclude-standard -z -- . ':!:tests' ':!:docs' ':!:bags' \
    | tar --null -T - -cf -) | (cd "$dest" && tar -xf -)
(cd "$src" && tar --exclude=__pycache__ -cf - tests/__init__.py tests/sim_core/__init__.py tests/support \
    tests/sim_core/ti_kernels tests/sim_core/energies) | (cd "$dest" && tar -xf -)
du -sb "$dest"
