# Sourced by the GPU-side scripts (gpu_bench.sh, gpu_speed.sh) on a lent machine: installs the carried
# wheels of ${WHL} into /tmp/site once per machine and sets the environment that gsplat's JIT build and our
# code need (a warm machine reuses both the install and the build in .torch_ext).
if [ ! -f /tmp/site/.jsgs_ok ]; then
    python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site \
        "$WHL"/*.whl && touch /tmp/site/.jsgs_ok || exit 1
fi
export PYTHONPATH=/tmp/site:$PWD PYTHONUNBUFFERED=1 OMP_NUM_THREADS=4
export TORCH_EXTENSIONS_DIR=$PWD/.torch_ext TORCH_CUDA_ARCH_LIST=9.0 MAX_JOBS=16
