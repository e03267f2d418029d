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
if [ ! -x "$venv/bin/python" ]; then
  if ! python3 -m venv "$venv" >/dev/null 2>&1; then
    # Debian's python3 keeps venv (and the pip it installs) in a package of its own.
    rm -rf "$venv"
    sudo=""
    [ "$(id -u)" -eq 0 ] || sudo="sudo"
    echo "installing: python3-venv" >&2
    DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -qq --no-install-recommends python3-venv >/dev/null
    python3 -m venv "$venv"
  fi
fi
"$venv/bin/python" -m pip install -q --upgrade pip
"$venv/bin/python" -m pip install -q "./python[torch,jax,test]"
"$venv/bin/python" -c "import volgrad, torch; print('volgrad for Python in $venv (torch', torch.__version__ + ')')"
