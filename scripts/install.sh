#!/usr/bin/env bash
# Install como3r into the active Python environment.
#   bash scripts/install.sh          the package and the command `como3r`
#   bash scripts/install.sh test     the same plus the test extras and the viewer extra
#                                    (tests/viewer reads rerun recordings back)
# torch, in this order:
#   an installed torch (for example a CUDA build) is kept;
#   COMO3R_TORCH="<requirement>" installs that requirement instead of the choice below;
#   a machine with an NVIDIA driver gets PyPI's default (CUDA) build;
#   any other machine gets torch==2.13.0 from PyTorch's CPU-only index (the one pytorch.org's
#   install selector gives for CPU); if that index cannot be reached, it says so and falls
#   back to PyPI's torch==2.13.0 (on Linux the CUDA build).
#   COMO3R_TORCH_INDEX="<url>" installs torch from that package index instead (no fallback).
#   COMO3R_INSTALL_DRY_RUN=1 prints the pip commands instead of running them.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python}
TORCH_PIN="torch==2.13.0"
CPU_INDEX="https://download.pytorch.org/whl/cpu"
INDEX=${COMO3R_TORCH_INDEX:-}
DRY_RUN=${COMO3R_INSTALL_DRY_RUN:-0}

pip_install() {
    if [ "$DRY_RUN" = "1" ]; then
        echo "como3r: would run: $PY -m pip install $*"
    else
        "$PY" -m pip install "$@"
    fi
}

# Whether a package index answers within 10 s (any HTTP answer, or a TLS handshake pip may
# accept with its own certificates, counts). pip alone cannot tell: with find-links or an extra
# index in the user's pip configuration, an unreachable --index-url is skipped silently.
index_reachable() {
    "$PY" -c '
import ssl, sys, urllib.error, urllib.request
try:
    urllib.request.urlopen(sys.argv[1], timeout=10)
except urllib.error.HTTPError:
    pass
except urllib.error.URLError as exc:
    sys.exit(0 if isinstance(exc.reason, ssl.SSLError) else 1)
except OSError:
    sys.exit(1)
' "$1/torch/" >/dev/null 2>&1
}

index_args=()
if [ -n "$INDEX" ]; then index_args=(--index-url "$INDEX"); fi

if "$PY" -c "import torch" >/dev/null 2>&1; then
    echo "como3r: keeping the installed torch $("$PY" -c 'import torch; print(torch.__version__)')"
elif [ -n "${COMO3R_TORCH:-}" ]; then
    pip_install ${index_args[@]+"${index_args[@]}"} "$COMO3R_TORCH"
elif command -v nvidia-smi >/dev/null 2>&1 && nvidia-smi -L >/dev/null 2>&1; then
    pip_install ${index_args[@]+"${index_args[@]}"} "torch>=2.4"
elif [ -n "$INDEX" ]; then
    pip_install --index-url "$INDEX" "$TORCH_PIN"
elif ! index_reachable "$CPU_INDEX" \
        || ! pip_install --index-url "$CPU_INDEX" --timeout 10 --retries 0 "$TORCH_PIN"; then
    echo "como3r: PyTorch's CPU index $CPU_INDEX could not be reached; falling back to" \
         "PyPI's $TORCH_PIN (on Linux the CUDA build: about 530 MB plus a few GB of NVIDIA" \
         "libraries)" >&2
    pip_install "$TORCH_PIN"
fi
extras=""
if [ "${1:-}" = "test" ]; then extras="[test,viewer]"; fi
pip_install -e ".${extras}"
