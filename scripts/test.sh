#!/usr/bin/env bash
# The whole test suite, as CI runs it: the Rust tests (statistical ones included: optimised), then
# the Python package's, in the virtual environment setup-python.sh makes.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh   # does nothing when the system libraries are there
cargo test --release
bash scripts/setup-python.sh
.venv/bin/python -m pytest -q python/tests
