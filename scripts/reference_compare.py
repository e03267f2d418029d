"""What `mitsuba_reference.py` and `cycles_reference.py` share: their common arguments, the passes
(volgrad's render and the other renderer's, seed by seed), image means over blocks, and the
comparison of the two renderers' passes against the passes' own noise."""

import argparse
import pathlib
import subprocess
import sys
import tempfile
import tomllib

import numpy as np


def spectrum(value):
    """A scene file's grey or [r, g, b] value as three floats."""
    return [float(value)] * 3 if isinstance(value, (int, float)) else [float(v) for v in value]


def arguments(description):
    """The options both scripts take; a script adds its own before `resolved`."""
    parser = argparse.ArgumentParser(description=description)
    parser.add_argument("scene", type=pathlib.Path)
    parser.add_argument("--spp", type=int, default=64, help="samples per pixel in each pass")
    parser.add_argument("--passes", type=int, default=8, help="passes per renderer (seeds 1..N)")
    parser.add_argument("--blocks", type=int, default=4, help="blocks per image side")
    parser.add_argument("--max-depth", type=int, help="scattering events (default: the scene's)")
    parser.add_argument("--volgrad", default="target/release/volgrad")
    parser.add_argument("--out", type=pathlib.Path, help="keep the EXRs here")
    return parser


def resolved(parser, theirs):
    """(args, the scene file parsed, the output folder, max_depth), after the checks: at least two
    passes (the noise is estimated from them), and no EXR of these passes already in `--out`."""
    args = parser.parse_args()
    if args.passes < 2:
        sys.exit("error: --passes must be at least 2 (the noise is estimated from the passes)")
    scene = tomllib.loads(args.scene.read_text())
    out = args.out or pathlib.Path(tempfile.mkdtemp(prefix=f"{theirs}-reference-"))
    out.mkdir(parents=True, exist_ok=True)
    for name in ("volgrad", theirs):
        for seed in range(1, args.passes + 1):
            if (out / f"{name}-{seed}.exr").exists():
                sys.exit(f"error: {out / f'{name}-{seed}.exr'} already exists; give another --out")
    max_depth = args.max_depth
    if max_depth is None:
        max_depth = scene.get("render", {}).get("max_depth", 64)
    return args, scene, out, max_depth


def compare_passes(args, out, max_depth, theirs, render_theirs, read_exr):
    """Renders `args.passes` passes with volgrad and with `render_theirs(seed, path)` (which writes
    an EXR), reads each back with `read_exr` and prints the comparison."""
    means = {"volgrad": [], theirs: []}
    for seed in range(1, args.passes + 1):
        exr = out / f"volgrad-{seed}.exr"
        volgrad = subprocess.run(
            [args.volgrad, "render", str(args.scene), "--spp", str(args.spp), "--seed", str(seed),
             "--max-depth", str(max_depth), "--quiet", "--output", str(exr)],
        )
        if volgrad.returncode != 0:
            sys.exit(f"error: `{args.volgrad} render` failed (its message is above)")
        means["volgrad"].append(block_means(read_exr(exr), args.blocks))
        exr = out / f"{theirs}-{seed}.exr"
        render_theirs(seed, exr)
        means[theirs].append(block_means(read_exr(exr), args.blocks))
        print(f"pass {seed}/{args.passes}", file=sys.stderr)
    report(args.scene, args.spp, means, "volgrad", theirs, args.blocks)


def block_means(image, blocks):
    """Per-channel means of the whole image and of a blocks × blocks grid of tiles."""
    h, w, _ = image.shape
    rows = np.array_split(np.arange(h), blocks)
    cols = np.array_split(np.arange(w), blocks)
    tiles = [image[np.ix_(r, c)].reshape(-1, 3).mean(axis=0) for r in rows for c in cols]
    return np.vstack([image.reshape(-1, 3).mean(axis=0)] + tiles)


def report(scene, spp, means, ours, theirs, blocks):
    """Prints the difference of the passes' means (`means[name]`: one `block_means` per pass) in
    units of its standard error, whole image and per block."""
    m = {k: np.array(v) for k, v in means.items()}  # passes × (1 + blocks²) × 3
    passes = len(m[ours])
    mean = {k: v.mean(axis=0) for k, v in m.items()}
    error = {k: v.std(axis=0, ddof=1) / np.sqrt(passes) for k, v in m.items()}
    difference = mean[ours] - mean[theirs]
    noise = np.sqrt(error[ours] ** 2 + error[theirs] ** 2)
    # Blocks of background alone are exact in both (every path escapes at once): no noise, and
    # equal values give z = 0; a difference there is infinitely significant.
    with np.errstate(divide="ignore", invalid="ignore"):
        z = np.where(noise > 0, difference / noise, np.where(difference == 0, 0.0, np.inf))
        relative = np.where(mean[theirs] != 0, difference / mean[theirs], 0.0)
    print(f"{scene}: {passes} passes of {spp} spp per renderer")
    for c, name in enumerate("RGB"):
        print(
            f"  {name}: image mean {ours} {mean[ours][0, c]:.5f} ± {error[ours][0, c]:.5f}, "
            f"{theirs} {mean[theirs][0, c]:.5f} ± {error[theirs][0, c]:.5f} "
            f"({100 * relative[0, c]:+.2f} %, z = {z[0, c]:+.2f})"
        )
    print(
        f"  {blocks}×{blocks} blocks × 3 channels: |z| ≤ {np.abs(z[1:]).max():.2f} "
        f"(largest relative difference {100 * np.abs(relative[1:]).max():.2f} %)"
    )
    print("  z per block (channel of largest |z|):")
    worst = np.abs(z[1:]).max(axis=1).reshape(blocks, blocks)
    for row in worst:
        print("   " + " ".join(f"{v:5.2f}" for v in row))
