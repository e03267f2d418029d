#!/usr/bin/env bash
# Regenerates the small analytic grids in scenes/analytic/ with `volgrad make-grid`.
set -euo pipefail
cd "$(dirname "$0")/analytic"
vg() { cargo run --quiet --release -- "$@"; }
vg make-grid box          --size 16 --value 1   --voxel-size 0.25 -o box.vdb          --force
vg make-grid sphere       --size 24 --value 1   --voxel-size 0.25 -o sphere.vdb       --force
vg make-grid slab         --size 32 --thickness 2 --value 1 --voxel-size 0.25 --rotate-deg 60,0,20 -o slab.vdb --force
vg make-grid single-voxel --size 9  --value 50  --voxel-size 0.5  -o single-voxel.vdb --force
vg make-grid fireball     --size 32 --value 2   --voxel-size 0.25 -o fireball.vdb     --force
vg make-grid coloured-smoke --size 32 --value 2 --voxel-size 0.25 -o coloured-smoke.vdb --force
