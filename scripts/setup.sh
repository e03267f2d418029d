#!/usr/bin/env bash
# Installs the system libraries volgrad builds against (Debian 12): OpenVDB, OpenImageIO, and the
# headers OpenVDB needs but does not pull in (boost, TBB), and vdb_print. Does nothing when they are
# present.
set -euo pipefail

# fonts-dejavu-core: the labels of the PNG charts of `volgrad compare` (src/io/chart.rs).
# libopenmpi-dev, openmpi-bin, libclang-dev: running across ranks (the `mpi` feature, on by
# default; rsmpi's build generates its bindings with libclang), and mpirun for the tests.
# python3-venv: the Python package's virtual environment (setup-python.sh), so that after this
# script nothing else needs root.
packages=(libopenvdb-dev libopenimageio-dev libboost-dev libtbb-dev g++ libopenvdb-tools fonts-dejavu-core
  libopenmpi-dev openmpi-bin libclang-dev python3-venv)
missing=()
for p in "${packages[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
if [ ${#missing[@]} -eq 0 ]; then
  exit 0
fi
echo "installing: ${missing[*]}" >&2
sudo=""
if [ "$(id -u)" -ne 0 ]; then
  command -v sudo >/dev/null || { echo "need root (or sudo) to apt-get install ${missing[*]}" >&2; exit 1; }
  sudo="sudo"
fi
# Through env: sudo's env_reset would drop an exported DEBIAN_FRONTEND, and a question debconf
# asked with its output sent to /dev/null would look like a hang.
$sudo env DEBIAN_FRONTEND=noninteractive apt-get update -qq
$sudo env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
