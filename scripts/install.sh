#!/usr/bin/env bash
# Install como3r into the active Python environment.
#   bash scripts/install.sh          the package and the command `como3r`
#   bash scripts/install.sh test     the same plus the test extras
# torch: an installed torch (for example a CUDA build) is kept. Otherwise a machine with
# an NVIDIA driver gets PyPI's default (CUDA) build and any other machine the CPU build
# torch==2.13.0 (set COMO3R_TORCH to choose another requirement).
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python}
if "$PY" -c "import torch" >/dev/null 2>&1; then
    echo "como3r: keeping the installed torch $("$PY" -c 'import torch; print(torch.__version__)')"
elif [ -n "${COMO3R_TORCH:-}" ]; then
    "$PY" -m pip install "$COMO3R_TORCH"
elif command -v nvidia-smi >/dev/null 2>&1 && nvidia-smi -L >/dev/null 2>&1; then
    "$PY" -m pip install "torch>=2.4"
else
    "$PY" -m pip install "torch==2.13.0"
fi
extras=""
if [ "${1:-}" = "test" ]; then extras="[test]"; fi
"$PY" -m pip install -e ".${extras}"
