#!/usr/bin/env bash
# Copy this checkout's code (no .git, docs, bags; of the tests only the Taichi kernel tests and their
# support, which run on CUDA with THINSHELL_TEST_ARCH=cuda) into DEST (default ../main/.gpu_src), the folder
# the `device` tool carries to the GPU machine when the device copies another checkout's working tree.
set -eu
src=$(cd "$(dirname "$0")/.." && pwd)
dest=${1:-/work/main/.gpu_src}
rm -rf "$dest"
mkdir -p "$dest"
# the checkout's files that git tracks or would track (not its ignored venv, build outputs, caches)
(cd "$src" && git ls-files -co --exclude-standard -z -- . ':!:tests' ':!:docs' ':!:bags' \
    | tar --null -T - -cf -) | (cd "$dest" && tar -xf -)
(cd "$src" && tar --exclude=__pycache__ -cf - tests/__init__.py tests/sim_core/__init__.py tests/support \
    tests/sim_core/ti_kernels tests/sim_core/energies) | (cd "$dest" && tar -xf -)
du -sb "$dest"
