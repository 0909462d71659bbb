#!/usr/bin/env bash
# Builds .venv with everything the project needs. Idempotent: a finished venv is reused.
# On a machine without CUDA, CPU torch must be installed from the pinned local build *before* anything that
# depends on torch, or pip pulls gigabytes of CUDA wheels. Where a CUDA torch is already present in the
# system Python, the venv sees it (--system-site-packages) and nothing replaces it.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
VENV=.venv
STAMP=$VENV/.jsgs-installed

# The viewer's browser test screenshots the page with Debian's chromium (headless); installed where apt-get can
# (as root), else that one test skips with its reason.
if ! command -v chromium >/dev/null 2>&1 && command -v apt-get >/dev/null 2>&1 && [ "$(id -u)" = 0 ]; then
    echo "setup: installing chromium (the viewer's browser test)"
    { apt-get install -y -q --no-install-recommends chromium >/dev/null 2>&1 \
        || { apt-get update -q >/dev/null 2>&1 && apt-get install -y -q --no-install-recommends chromium >/dev/null 2>&1; }; } \
        || echo "setup: chromium could not be installed; the viewer's browser test will skip"
fi

if [ -f "$STAMP" ] && [ "$STAMP" -nt pyproject.toml ]; then
    exit 0
fi

cuda_torch=$("$PY" -c 'import torch; print(int(torch.cuda.is_available()))' 2>/dev/null || echo 0)
if [ ! -x "$VENV/bin/python" ]; then
    if [ "$cuda_torch" = "1" ]; then
        echo "setup: CUDA torch found in $PY; the venv reuses it"
        "$PY" -m venv --system-site-packages "$VENV"
    else
        "$PY" -m venv "$VENV"
    fi
fi
"$VENV/bin/python" -m pip install -q --upgrade pip
if ! "$VENV/bin/python" -c 'import torch' 2>/dev/null; then
    echo "setup: installing CPU torch 2.13.0"
    "$VENV/bin/python" -m pip install -q torch==2.13.0
fi
echo "setup: installing jsgs and its dependencies"
"$VENV/bin/python" -m pip install -q -e ".[test]"
touch "$STAMP"
