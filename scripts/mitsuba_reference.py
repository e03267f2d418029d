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

import json
import pathlib
import subprocess
import sys
import tempfile

import numpy as np

from reference_compare import arguments, compare_passes, resolved, spectrum


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


def main():
    parser = arguments(__doc__.split("\n\n")[0])
    parser.add_argument("--exporter", default="target/release/examples/mitsuba_volume")
    args, scene, out, max_depth = resolved(parser, "mitsuba")

    import mitsuba as mi

    mi.set_variant("scalar_rgb")
    work = pathlib.Path(tempfile.mkdtemp(prefix="mitsuba-volume-"))
    if subprocess.run([args.exporter, str(args.scene), str(work)]).returncode != 0:
        sys.exit(f"error: `{args.exporter}` failed (its message is above)")
    volume = json.loads((work / "volume.json").read_text())
    reference = mi.load_dict(mitsuba_scene(mi, scene, work, volume, max_depth))

    def render(seed, exr):
        image = np.array(mi.render(reference, spp=args.spp, seed=seed))[:, :, :3]
        mi.Bitmap(image).write(str(exr))

    def read_exr(exr):
        return np.array(mi.Bitmap(str(exr)))[:, :, :3]

    compare_passes(args, out, max_depth, "mitsuba", render, read_exr)


if __name__ == "__main__":
    main()
