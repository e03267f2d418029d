#!/usr/bin/env python3
"""Makes a multi-view capture of a volgrad scene with Blender's Cycles, as a user would bring it to
`volgrad optimize`: 8-bit sRGB PNGs with alpha and NeRF `transforms_*.json` cameras.

    python3 -m venv /tmp/bpy && /tmp/bpy/bin/pip install bpy==4.2.0     # Python 3.11
    /tmp/bpy/bin/python scripts/make-capture.py scenes/capture/plume-scene.toml scenes/capture/plume

Cycles is set up from the scene file by `cycles_reference.py` (the mapping validated there against
volgrad: density × density_scale, albedo, Henyey-Greenstein phase, `constant` lights as the world's
colour, `directional` ones as sun lamps of angle 0 whose strength is the irradiance, bounces =
max_depth − 1, no light tree), except the volume step: `--step-rate` is Cycles' own default, 1
voxel, where cycles_reference.py takes 0.05 — 20× slower on the smoke plume, and the same image means
(`capture_check.py` finds both within 0.25 % of volgrad at 64 spp). What this script adds:

- cameras on Fibonacci spirals as volgrad's `[views.orbit]` lays them out (equal steps in
  sin(elevation), azimuths a golden angle apart), looking at the scene camera's target from its
  distance (or `--centre`, `--distance`), square images of `--size` pixels, horizontal field of
  view `--fov`;
- `train/`: `--train` views under the scene's lights; `test/`: `--test` views on a second spiral
  turned by `--test-offset` degrees (between the training views), same lights; `relit/`: the test
  cameras under the scene's lights with every sun pointing along `--relit-direction` instead;
- each a PNG (8-bit, RGBA, sRGB): Film › Transparent, so that pixels where the camera sees only the
  sky have alpha 0 and the colour is the medium's alone; the Standard view transform (no Filmic/AgX
  curve, look None, exposure 0, gamma 1) and no dithering, so that the stored colour is the sRGB
  encoding of linear radiance (un-premultiplied by alpha, as PNG stores it). `--exr` also saves the
  same render (the same samples) as a linear half-float RGBA EXR (premultiplied) under `exr/`,
  with transforms files of its own;
- `transforms_{train,test,relit}.json`: `camera_angle_x`, `w`, `h`, and per frame `file_path` and
  `transform_matrix` (camera to world, rows; the camera looks down its −z with +y up: Blender's
  camera matrix as it is);
- `relit.toml`: the relit views as a run file's `[[holdout]]` tables (camera, image, lights) for a run
  file beside the capture's folder (a `[[holdouts]]` table with `transforms_relit.json` and the
  relit lights says the same in two lines, as `scenes/capture/plume.toml` does);
- `capture.json`: the arguments, the lights and the seconds each set took (not a transforms file).

Every image has its own Cycles seed (its index in the whole capture, from 1). `capture_check.py`
compares a capture with volgrad's render of the true grid from the same cameras. The PNG decoded from
sRGB and multiplied by its alpha equals the EXR of the same render to 0.05 % in the mean (8-bit
steps; straight colour above 1 is clipped in the PNG).
"""

import argparse
import json
import math
import pathlib
import sys
import time
import tomllib

from cycles_reference import cycles_lights, cycles_scene, look_at

GOLDEN_ANGLE = math.pi * (3.0 - math.sqrt(5.0))


def orbit(count, elevation_deg, distance, centre, up, azimuth_offset_deg):
    """volgrad's `[views.orbit]`: camera positions on a Fibonacci spiral about `up`."""
    import mathutils

    to_up = mathutils.Vector((0.0, 1.0, 0.0)).rotation_difference(mathutils.Vector(up).normalized())
    s_lo, s_hi = (math.sin(math.radians(e)) for e in elevation_deg)
    positions = []
    for i in range(count):
        s = s_lo + (s_hi - s_lo) * (i + 0.5) / count
        elevation, azimuth = math.asin(s), i * GOLDEN_ANGLE + math.radians(azimuth_offset_deg)
        offset = mathutils.Vector(
            (math.cos(elevation) * math.sin(azimuth), math.sin(elevation), math.cos(elevation) * math.cos(azimuth))
        )
        positions.append(mathutils.Vector(centre) + distance * (to_up @ offset))
    return positions


def arguments():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("scene", type=pathlib.Path, help="a volgrad scene file (TOML)")
    parser.add_argument("out", type=pathlib.Path, help="the capture's folder (must not hold one already)")
    parser.add_argument("--train", type=int, default=24, help="training views")
    parser.add_argument("--test", type=int, default=8, help="held-out views (and relit views)")
    parser.add_argument("--size", type=int, default=96, help="image width and height, pixels")
    parser.add_argument("--spp", type=int, default=256, help="Cycles samples per pixel")
    parser.add_argument("--fov", type=float, default=40.0, help="horizontal field of view, degrees")
    parser.add_argument("--distance", type=float, help="camera distance (default: the scene camera's)")
    parser.add_argument("--centre", type=float, nargs=3, help="what the cameras look at (default: the scene camera's target)")
    parser.add_argument("--up", type=float, nargs=3, help="the orbit's pole (default: the scene camera's up)")
    parser.add_argument("--elevation", type=float, nargs=2, default=[-30.0, 80.0], help="training band, degrees")
    parser.add_argument("--test-elevation", type=float, nargs=2, default=[-10.0, 60.0], help="held-out band, degrees")
    parser.add_argument("--test-offset", type=float, default=45.0, help="held-out spiral's azimuth offset, degrees")
    parser.add_argument("--relit-direction", type=float, nargs=3, default=[-0.8, -0.4, 0.6],
                        help="the direction the suns shine along in the relit views")
    parser.add_argument("--max-depth", type=int, help="scattering events (default: the scene's, else 64)")
    parser.add_argument("--step-rate", type=float, default=1.0, help="Cycles' volume step, in voxels (its own default)")
    parser.add_argument("--exr", action="store_true", help="also save linear EXRs of the same renders")
    return parser.parse_args()


def transforms_text(fov_deg, size, frames):
    """A transforms file's text: JSON, one line per matrix row."""
    lines = [
        "{",
        f'  "camera_angle_x": {json.dumps(math.radians(fov_deg))},',
        f'  "w": {size},',
        f'  "h": {size},',
        '  "frames": [',
    ]
    for i, frame in enumerate(frames):
        rows = ",\n".join(f"        {json.dumps(row)}" for row in frame["transform_matrix"])
        comma = "," if i + 1 < len(frames) else ""
        lines += [
            "    {",
            f'      "file_path": {json.dumps(frame["file_path"])},',
            f'      "transform_matrix": [\n{rows}\n      ]',
            "    }" + comma,
        ]
    return "\n".join(lines + ["  ]", "}"]) + "\n"


def matrix_rows(m):
    return [[float(m[r][c]) for c in range(4)] for r in range(4)]


def main():
    args = arguments()
    scene = tomllib.loads(args.scene.read_text())
    camera = scene["camera"]
    max_depth = args.max_depth or scene.get("render", {}).get("max_depth", 64)
    if max_depth < 1:
        sys.exit("error: --max-depth must be at least 1 (Cycles lights the first scattering at bounce 0)")
    if args.out.exists() and any(args.out.iterdir()):
        sys.exit(f"error: {args.out} is not empty")
    centre = args.centre or camera["target"]
    up = args.up or camera.get("up", [0.0, 1.0, 0.0])
    distance = args.distance or math.dist(camera["position"], camera["target"])
    lights = scene.get("light", [])
    relit_lights = [
        dict(light, direction=list(args.relit_direction)) if light["type"] == "directional" else light
        for light in lights
    ]
    if relit_lights == lights:
        sys.exit("error: the relit views need a directional light whose direction --relit-direction changes")

    import bpy

    blender = cycles_scene(bpy, args.scene, scene, max_depth, args.step_rate, None)
    blender.render.resolution_x = blender.render.resolution_y = args.size
    blender.render.film_transparent = True
    blender.render.dither_intensity = 0.0
    blender.display_settings.display_device = "sRGB"
    blender.view_settings.view_transform = "Standard"
    blender.view_settings.look = "None"
    blender.view_settings.exposure = 0.0
    blender.view_settings.gamma = 1.0
    blender.view_settings.use_curve_mapping = False
    blender.sequencer_colorspace_settings.name = "sRGB"
    blender.cycles.samples = args.spp
    lens = blender.camera.data
    lens.sensor_fit = "HORIZONTAL"
    lens.angle = math.radians(args.fov)

    png = {"file_format": "PNG", "color_mode": "RGBA", "color_depth": "8", "compression": 100}
    exr = {"file_format": "OPEN_EXR", "color_mode": "RGBA", "color_depth": "16", "exr_codec": "ZIP"}

    def save(path, settings):
        image_settings = blender.render.image_settings
        for key, value in settings.items():
            setattr(image_settings, key, value)
        bpy.data.images["Render Result"].save_render(filepath=str(path), scene=blender)

    sets = {
        "train": (orbit(args.train, args.elevation, distance, centre, up, 0.0), lights),
        "test": (orbit(args.test, args.test_elevation, distance, centre, up, args.test_offset), lights),
    }
    sets["relit"] = (sets["test"][0], relit_lights)
    seconds, seed = {}, 0
    relit_views = []
    for name, (positions, set_lights) in sets.items():
        cycles_lights(bpy, blender, set_lights)
        frames, exr_frames = [], []
        start = time.monotonic()
        for i, position in enumerate(positions):
            seed += 1
            blender.camera.matrix_world = look_at(position, centre, up)
            blender.cycles.seed = seed
            bpy.ops.render.render(write_still=False)
            stem = f"{name}/r_{i:03d}"
            (args.out / name).mkdir(parents=True, exist_ok=True)
            save(args.out / f"{stem}.png", png)
            matrix = matrix_rows(blender.camera.matrix_world)
            frames.append({"file_path": f"{stem}.png", "transform_matrix": matrix})
            if args.exr:
                (args.out / "exr" / name).mkdir(parents=True, exist_ok=True)
                save(args.out / "exr" / f"{stem}.exr", exr)
                exr_frames.append({"file_path": f"{stem}.exr", "transform_matrix": matrix})
            if name == "relit":
                relit_views.append((position, f"{args.out.name}/{stem}.png"))
            print(f"{stem}: {time.monotonic() - start:.1f} s", file=sys.stderr)
        seconds[name] = time.monotonic() - start
        (args.out / f"transforms_{name}.json").write_text(
            transforms_text(args.fov, args.size, frames)
        )
        if args.exr:
            (args.out / "exr" / f"transforms_{name}.json").write_text(
                transforms_text(args.fov, args.size, exr_frames)
            )

    def toml_value(v):
        if isinstance(v, (list, tuple)):
            return "[" + ", ".join(toml_value(x) for x in v) + "]"
        if isinstance(v, str):
            return json.dumps(v)
        if isinstance(v, dict):
            return "{ " + ", ".join(f"{k} = {toml_value(x)}" for k, x in v.items()) + " }"
        return repr(float(v)) if isinstance(v, float) else str(v)

    relit = [
        "# The relit views as a run file's held-out views: the test cameras under a sun shining along",
        f"# {toml_value(args.relit_direction)}. Image paths are relative to the folder that holds the",
        "# capture's folder: paste them into a run file there.",
    ]
    for position, image in relit_views:
        relit += [
            "",
            "[[holdout]]",
            f"position = {toml_value([round(float(x), 6) for x in position])}",
            f"target = {toml_value([float(x) for x in centre])}",
            f"up = {toml_value([float(x) for x in up])}",
            f"fov_deg = {toml_value(float(args.fov))}",
            f"width = {args.size}",
            f"height = {args.size}",
            f"image = {toml_value(image)}",
            f"light = {toml_value(relit_lights)}",
        ]
    (args.out / "relit.toml").write_text("\n".join(relit) + "\n")
    record = {
        "command": sys.argv,
        "arguments": {k: str(v) if isinstance(v, pathlib.Path) else v for k, v in vars(args).items()},
        "blender": bpy.app.version_string,
        "scene": str(args.scene),
        "max_depth": max_depth,
        "lights": lights,
        "relit_lights": relit_lights,
        "seconds": {k: round(v, 1) for k, v in seconds.items()},
    }
    (args.out / "capture.json").write_text(json.dumps(record, indent=2) + "\n")
    print(f"{args.out}: {', '.join(f'{k} {v:.0f} s' for k, v in seconds.items())}", file=sys.stderr)


if __name__ == "__main__":
    main()
