#!/usr/bin/env bash
# The Python package in a virtual environment (default .venv/ at the repository's top): volgrad
# built from python/ by maturin against the system libraries setup.sh installs, numpy, PyTorch
# (PyPI's wheel, used on the CPU), JAX (CPU), and the tests' own needs (pytest; OpenEXR, an EXR
# reader that is not volgrad's). Does little when they are there already.
#
#   scripts/setup-python.sh [VENV]
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
venv=${1:-.venv}
# A venv without a working pip (made by hand without python3-venv, or cut short) is made again.
if ! "$venv/bin/python" -m pip --version >/dev/null 2>&1; then
  rm -rf "$venv"
  python3 -m venv "$venv"
fi
"$venv/bin/python" -m pip install -q --upgrade pip
"$venv/bin/python" -m pip install -q "./python[torch,jax,test]"
"$venv/bin/python" -c "import volgrad, torch; print('volgrad for Python in $venv (torch', torch.__version__ + ')')"
