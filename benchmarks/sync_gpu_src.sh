#!/usr/bin/env bash
# Copy this checkout's code (no .git, tests, docs, bags) into DEST (default ../main/.gpu_src), the folder
# the `device` tool carries to the GPU machine when the device copies another checkout's working tree.
set -eu
src=$(cd "$(dirname "$0")/.." && pwd)
dest=${1:-/work/main/.gpu_src}
rm -rf "$dest"
mkdir -p "$dest"
(cd "$src" && tar --exclude=.git --exclude=./tests --exclude=./docs --exclude=./bags --exclude=__pycache__ \
    --exclude=.pytest_cache -cf - .) | (cd "$dest" && tar -xf -)
du -sb "$dest"
