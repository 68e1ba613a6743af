#!/usr/bin/env bash
# Create .venv and install eofnn with its test dependencies. Torch is installed first from the CPU build
# (a bare `torch` requirement would otherwise pull a multi-GB CUDA build); the range in pyproject then holds.
set -euo pipefail
cd "$(dirname "$0")/.."
[ -x .venv/bin/python ] || python3 -m venv .venv
.venv/bin/python -c "import torch" 2>/dev/null || .venv/bin/python -m pip install -q "torch==2.13.0"
.venv/bin/python -m pip install -q -e ".[test]"
