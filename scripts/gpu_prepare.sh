#!/usr/bin/env bash
# CPU side of a GPU session (run here, before the device call): the wheels the GPU machine lacks and the
# clean bases it derives its datasets from, in git-ignored folders that the device tool carries.
#   GPU_DIR=.gpuB GPU_SCENES="llff_flower llff_fern" bash scripts/gpu_prepare.sh   # then carry [".whl", ".gpuB"]
# The GPU image already has torch 2.11 + CUDA, click, tqdm, rich, pytest, ninja, matplotlib, Pillow and numpy
# (see the device tool's KINDS.md); it lacks gsplat and jsonschema. It compiles gsplat's CUDA code on first
# use (about 60-80 s). One call carries at most 64 MiB: the four shared scenes' clean bases (7-11 MiB each
# as kept here), the 9.5 MiB LPIPS backbone and 7 MiB of wheels fit (57 MiB). Then run
# `bash scripts/gpu_run.sh <command>` there.
set -euo pipefail
cd "$(dirname "$0")/.."
G=${GPU_DIR:-.gpu}
W=${WHL:-.whl}
mkdir -p "$W" "$G"
python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
    --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 \
    -d "$W" gsplat==1.5.3 jsonschema jsonschema-specifications referencing rpds-py
# One clean base per scene (manifest.json, compress.json, reference/; images/ and sparse/ dropped, since the
# manifest holds the cameras and points): on the GPU machine `jsgs bench` derives every JPEG dataset from it
# with Pillow alone, and trains the clean runs on it.
for scene in ${GPU_SCENES:-llff_flower}; do
    d=$G/bench/data/$scene/clean_s0
    [ -f "$d/manifest.json" ] || \
        .venv/bin/jsgstools compress "../shared/scenes/$scene" --out "$d" --schedule clean --seed 0 --force
    rm -rf "$d/images" "$d/sparse"
done
[ -f "$G/alexnet_features.pth" ] || cp ../shared/lpips/alexnet_features.pth "$G/" 2>/dev/null \
    || echo "no LPIPS weights: LPIPS will be null"
du -sh "$W" "$G"
