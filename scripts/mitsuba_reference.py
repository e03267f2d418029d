#!/usr/bin/env python3
"""An independent forward reference: renders a volgrad scene with Mitsuba 3 (`pip install
mitsuba`, the scalar_rgb variant) and with volgrad, several passes each with their own seeds, and
compares the image means, overall and over a grid of blocks, against the passes' own noise.

    cargo build --release --examples
    python3 scripts/mitsuba_reference.py scenes/coloured-smoke.toml --spp 64 --passes 8

Both renderers see the same medium: `examples/mitsuba_volume.rs` writes volgrad's loaded grids as
Mitsuba volumes (see there how the edges are matched), and this script reads the scene file for the
camera, the lights, the density scale, the phase function and the depth. What it maps:

- camera: `perspective` with `fov_axis = "x"` (volgrad's field of view is horizontal), look_at;
  a box pixel filter (volgrad averages uniform samples over each pixel);
- `constant` → `constant` (radiance), `directional` → `directional` (the direction light travels,
  irradiance); an envmap is refused (its parametrisation is Mitsuba's, but not tested here);
- the medium: `heterogeneous` with `sigma_t` = the density volume × density_scale, the albedo
  (constant or the volume), `hg` with g; it lives inside a `cube` with a `null` BSDF;
- depth: volgrad's max_depth counts scattering events; Mitsuba's `max_depth` counts path
  vertices including the camera's ray, so it is volgrad's + 1.

Emission is not compared: Mitsuba 3's heterogeneous medium has none.
"""

import argparse
import json
import pathlib
import subprocess
import sys
import tempfile
import tomllib

import numpy as np


def spectrum(value):
    return [float(value)] * 3 if isinstance(value, (int, float)) else [float(v) for v in value]


def mitsuba_scene(mi, scene, volume_dir, volume, max_depth):
    camera, medium = scene["camera"], scene["medium"]
    width, height = camera["width"], camera["height"]
    sensor = {
        "type": "perspective",
        "fov_axis": "x",
        "fov": camera["fov_deg"],
        "to_world": mi.ScalarTransform4f().look_at(
            origin=camera["position"], target=camera["target"], up=camera.get("up", [0, 1, 0])
        ),
        "film": {
            "type": "hdrfilm",
            "width": width,
            "height": height,
            "pixel_format": "rgb",
            "rfilter": {"type": "box"},
        },
        "sampler": {"type": "independent"},
    }
    emitters = {}
    for i, light in enumerate(scene.get("light", [])):
        if light["type"] == "constant":
            emitters[f"light{i}"] = {
                "type": "constant",
                "radiance": {"type": "rgb", "value": spectrum(light["radiance"])},
            }
        elif light["type"] == "directional":
            emitters[f"light{i}"] = {
                "type": "directional",
                "direction": light["direction"],
                "irradiance": {"type": "rgb", "value": spectrum(light["irradiance"])},
            }
        else:
            sys.exit(f"error: light {i}: only constant and directional lights are mapped")
    grid_to_world = mi.ScalarTransform4f(volume["grid_to_world"])
    albedo = medium.get("albedo", 0.8)
    if isinstance(albedo, dict):
        albedo = {
            "type": "gridvolume",
            "filename": str(volume_dir / "albedo.vol"),
            "to_world": grid_to_world,
            "raw": True,
        }
    else:
        albedo = {"type": "constvolume", "value": {"type": "rgb", "value": spectrum(albedo)}}
    heterogeneous = {
        "type": "heterogeneous",
        "sigma_t": {
            "type": "gridvolume",
            "filename": str(volume_dir / "density.vol"),
            "to_world": grid_to_world,
        },
        "scale": float(medium.get("density_scale", 1.0)),
        "albedo": albedo,
        "phase": {"type": "hg", "g": float(medium.get("phase_g", 0.0))},
    }
    return {
        "type": "scene",
        "integrator": {"type": "volpath", "max_depth": max_depth + 1},
        "sensor": sensor,
        "box": {
            "type": "cube",
            "to_world": mi.ScalarTransform4f(volume["shape_to_world"]),
            "bsdf": {"type": "null"},
            "interior": heterogeneous,
        },
        **emitters,
    }


def block_means(image, blocks):
    """Per-channel means of the whole image and of a blocks × blocks grid of tiles."""
    h, w, _ = image.shape
    rows = np.array_split(np.arange(h), blocks)
    cols = np.array_split(np.arange(w), blocks)
    tiles = [image[np.ix_(r, c)].reshape(-1, 3).mean(axis=0) for r in rows for c in cols]
    return np.vstack([image.reshape(-1, 3).mean(axis=0)] + tiles)


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("scene", type=pathlib.Path)
    parser.add_argument("--spp", type=int, default=64, help="samples per pixel in each pass")
    parser.add_argument("--passes", type=int, default=8, help="passes per renderer (seeds 1..N)")
    parser.add_argument("--blocks", type=int, default=4, help="blocks per image side")
    parser.add_argument("--max-depth", type=int, help="scattering events (default: the scene's)")
    parser.add_argument("--volgrad", default="target/release/volgrad")
    parser.add_argument("--exporter", default="target/release/examples/mitsuba_volume")
    parser.add_argument("--out", type=pathlib.Path, help="keep the EXRs here")
    args = parser.parse_args()
    if args.passes < 2:
        sys.exit("error: --passes must be at least 2 (the noise is estimated from the passes)")

    import mitsuba as mi

    mi.set_variant("scalar_rgb")
    scene = tomllib.loads(args.scene.read_text())
    work = pathlib.Path(tempfile.mkdtemp(prefix="mitsuba-reference-"))
    out = args.out or work
    out.mkdir(parents=True, exist_ok=True)
    subprocess.run([args.exporter, str(args.scene), str(work)], check=True)
    volume = json.loads((work / "volume.json").read_text())
    max_depth = args.max_depth
    if max_depth is None:
        max_depth = scene.get("render", {}).get("max_depth", 64)
    reference = mi.load_dict(mitsuba_scene(mi, scene, work, volume, max_depth))

    means = {"volgrad": [], "mitsuba": []}
    for seed in range(1, args.passes + 1):
        exr = out / f"volgrad-{seed}.exr"
        subprocess.run(
            [args.volgrad, "render", str(args.scene), "--spp", str(args.spp), "--seed", str(seed),
             "--max-depth", str(max_depth), "--quiet", "--output", str(exr)],
            check=True,
        )
        image = np.array(mi.Bitmap(str(exr)))[:, :, :3]
        means["volgrad"].append(block_means(image, args.blocks))
        image = np.array(mi.render(reference, spp=args.spp, seed=seed))[:, :, :3]
        mi.Bitmap(image).write(str(out / f"mitsuba-{seed}.exr"))
        means["mitsuba"].append(block_means(image, args.blocks))
        print(f"pass {seed}/{args.passes}", file=sys.stderr)

    m = {k: np.array(v) for k, v in means.items()}  # passes × (1 + blocks²) × 3
    mean = {k: v.mean(axis=0) for k, v in m.items()}
    error = {k: v.std(axis=0, ddof=1) / np.sqrt(args.passes) for k, v in m.items()}
    difference = mean["volgrad"] - mean["mitsuba"]
    noise = np.sqrt(error["volgrad"] ** 2 + error["mitsuba"] ** 2)
    # Blocks of background alone are exact in both (every path escapes at once): no noise, and
    # equal values give z = 0; a difference there is infinitely significant.
    with np.errstate(divide="ignore", invalid="ignore"):
        z = np.where(noise > 0, difference / noise, np.where(difference == 0, 0.0, np.inf))
        relative = np.where(mean["mitsuba"] != 0, difference / mean["mitsuba"], 0.0)
    print(f"{args.scene}: {args.passes} passes of {args.spp} spp per renderer")
    for c, name in enumerate("RGB"):
        print(
            f"  {name}: image mean volgrad {mean['volgrad'][0, c]:.5f} ± {error['volgrad'][0, c]:.5f}, "
            f"mitsuba {mean['mitsuba'][0, c]:.5f} ± {error['mitsuba'][0, c]:.5f} "
            f"({100 * relative[0, c]:+.2f} %, z = {z[0, c]:+.2f})"
        )
    print(
        f"  {args.blocks}×{args.blocks} blocks × 3 channels: |z| ≤ {np.abs(z[1:]).max():.2f} "
        f"(largest relative difference {100 * np.abs(relative[1:]).max():.2f} %)"
    )
    print("  z per block (channel of largest |z|):")
    worst = np.abs(z[1:]).max(axis=1).reshape(args.blocks, args.blocks)
    for row in worst:
        print("   " + " ".join(f"{v:5.2f}" for v in row))


if __name__ == "__main__":
    main()
