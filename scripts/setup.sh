#!/usr/bin/env bash
# Create .venv and install eofnn with its test dependencies and the interop extra (OOPAO). Torch is installed first, as the CPU build
# (a bare `torch` requirement pulls the CUDA build: about 900 MB plus several GB of nvidia-* wheels); the range in
# pyproject then holds.
#   - EOFNN_TORCH_INDEX=https://download.pytorch.org/whl/cpu bash scripts/setup.sh   # the CPU build, explicitly
#   - without it, pip's own configuration decides (a local CPU wheel in find-links, as on CI): before installing,
#     the script says which wheel pip picked, and warns when it is not a CPU build.
set -euo pipefail
cd "$(dirname "$0")/.."
TORCH="torch==2.13.0"
[ -x .venv/bin/python ] || python3 -m venv .venv
if ! .venv/bin/python -c "import torch" 2>/dev/null; then
    if [ -n "${EOFNN_TORCH_INDEX:-}" ]; then
        echo "eofnn setup: installing $TORCH from $EOFNN_TORCH_INDEX" >&2
        .venv/bin/python -m pip install -q --index-url "$EOFNN_TORCH_INDEX" "$TORCH"
    else
        url=$(.venv/bin/python -m pip install --dry-run --quiet --no-deps --report - "$TORCH" 2>/dev/null \
              | .venv/bin/python -c 'import json, sys; print(json.load(sys.stdin)["install"][0]["download_info"]["url"])' \
              || echo "unknown")
        echo "eofnn setup: installing $TORCH from $url" >&2
        case "$url" in
            *cpu*) ;;
            *) echo "eofnn setup: warning: that is not a CPU build: it downloads the CUDA build (several GB with its" \
                    "nvidia-* dependencies); for the CPU build (about 200 MB) interrupt and rerun with" \
                    "EOFNN_TORCH_INDEX=https://download.pytorch.org/whl/cpu" >&2 ;;
        esac
        .venv/bin/python -m pip install -q "$TORCH"
    fi
fi
# The interop extra (OOPAO, for eofnn/interop and its tests) comes with the test set-up: CI runs those tests.
.venv/bin/python -m pip install -q -e ".[test,interop]"
