#!/usr/bin/env bash
# Runs a command on a lent GPU machine whose Python has CUDA torch but lacks gsplat and jsonschema: installs
# the wheels carried in $WHL (made here by `scripts/gpu_prepare.sh`) into /tmp/site once per machine, points
# torch's extension cache at a folder of the checkout (a warm machine reuses gsplat's and jsgs's CUDA builds),
# then runs the command.
#   bash scripts/gpu_run.sh python3 -m pytest -m gpu tests
#   bash scripts/gpu_run.sh python3 -m jsgs.cli bench ...
set -euo pipefail
cd "$(dirname "$0")/.."
WHL=${WHL:-.whl}
if [ ! -f /tmp/site/.jsgs_ok ]; then
    python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site \
        "$WHL"/*.whl
    touch /tmp/site/.jsgs_ok
fi
export PYTHONPATH=/tmp/site:$PWD${PYTHONPATH:+:$PYTHONPATH} PYTHONUNBUFFERED=1 OMP_NUM_THREADS=${OMP_NUM_THREADS:-4}
export TORCH_EXTENSIONS_DIR=${TORCH_EXTENSIONS_DIR:-$PWD/.torch_ext} TORCH_CUDA_ARCH_LIST=${TORCH_CUDA_ARCH_LIST:-9.0}
export MAX_JOBS=${MAX_JOBS:-16} JSGS_LPIPS_DOWNLOAD=0
if [ -z "${JSGS_LPIPS_WEIGHTS:-}" ] && [ -f "${GPU_DIR:-.gpu}/alexnet_features.pth" ]; then
    JSGS_LPIPS_WEIGHTS=$(cd "${GPU_DIR:-.gpu}" && pwd)/alexnet_features.pth  # GPU_DIR relative or absolute
    export JSGS_LPIPS_WEIGHTS
fi
# Build (or load) gsplat's and jsgs's CUDA extensions once, under a lock, before the command: runs started side by
# side on an empty build folder would each try to build them, and all but one fail.
mkdir -p "$TORCH_EXTENSIONS_DIR"
flock "$TORCH_EXTENSIONS_DIR/.build.lock" python3 -c \
    "from gsplat.cuda._backend import _C; from jsgs.kernels import extension; extension()" >/dev/null
exec "$@"
