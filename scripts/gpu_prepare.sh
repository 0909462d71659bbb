#!/usr/bin/env bash
# CPU side of a GPU session (run here, before the device call): the wheels the GPU machine lacks and the
# clean bases it derives its datasets from, in git-ignored folders that the device tool carries (`carry: [".whl", ".gpu"]`).
# The GPU machine has torch 2.11 + CUDA but no internet and no gsplat; it compiles gsplat's CUDA code on
# first use (about 80 s). Then run scripts/gpu_session.sh there.
set -euo pipefail
cd "$(dirname "$0")/.."
mkdir -p .whl .gpu
python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
    --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 \
    -d .whl gsplat==1.5.3 jsonschema jsonschema-specifications referencing rpds-py attrs tqdm click \
    rich markdown-it-py mdurl pygments ninja pytest pluggy iniconfig
# One clean base per scene (manifest.json, compress.json, reference/; images/ dropped to halve the carry): on
# the GPU machine `jsgs bench ... --out .gpu/bench` derives every JPEG dataset from it with Pillow alone.
for scene in ${GPU_SCENES:-llff_flower}; do
    d=.gpu/bench/data/$scene/clean_s0
    [ -f "$d/manifest.json" ] || \
        .venv/bin/jsgstools compress "../shared/scenes/$scene" --out "$d" --schedule clean --seed 0 --force
    rm -rf "$d/images"
done
cp -n ../shared/lpips/alexnet_features.pth .gpu/ 2>/dev/null || echo "no LPIPS weights: LPIPS will be null"
du -sh .whl .gpu
