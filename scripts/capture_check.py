#!/usr/bin/env python3
"""Checks a capture made by `make-capture.py` against volgrad: renders the scene's true grid with
volgrad from each frame's camera under the set's lights, and compares it with the capture's image
as volgrad reads it (8-bit PNG decoded from sRGB, colour premultiplied by alpha and composited over
the constant sky; an EXR is premultiplied and linear already).

    cargo build --release
    /tmp/bpy/bin/python scripts/capture_check.py scenes/capture/plume-scene.toml scenes/capture/plume --set test

Prints, per view and over the set, the ratio of the image means (capture / volgrad, per channel;
over the whole image and over the pixels the medium covers, alpha > 0.05) and the PSNR as `volgrad optimize` computes it (10·log10(max(target)² / MSE), averaged over the
views): the set's ceiling, what the true grid scores against these images. Run with the Python
that has bpy (it reads volgrad's EXRs with Blender, as `cycles_reference.py` does) and Pillow.
"""

import argparse
import json
import math
import pathlib
import subprocess
import sys
import tempfile
import tomllib

import numpy as np

from reference_compare import spectrum


def srgb_decode(x):
    return np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4)


def read_rgba(path):
    """An image as rows top to bottom × columns × RGBA, linear, colour premultiplied."""
    if path.suffix.lower() == ".png":
        from PIL import Image

        stored = np.asarray(Image.open(path).convert("RGBA")).astype(np.float64) / 255.0
        alpha = stored[..., 3:4]
        return np.concatenate([srgb_decode(stored[..., :3]) * alpha, alpha], axis=-1)
    import bpy

    image = bpy.data.images.load(str(path))
    w, h = image.size
    pixels = np.array(image.pixels[:], dtype=np.float64).reshape(h, w, image.channels)[::-1]
    bpy.data.images.remove(image)
    if pixels.shape[-1] == 3:
        pixels = np.concatenate([pixels, np.ones(pixels.shape[:2] + (1,))], axis=-1)
    return pixels


def toml_value(v):
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(toml_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{ " + ", ".join(f"{k} = {toml_value(x)}" for k, x in v.items()) + " }"
    if isinstance(v, str):
        return json.dumps(v)
    return repr(v)


def toml_text(scene):
    """A scene file's text: tables, arrays of tables, inline tables inside them."""
    lines = []
    for key, value in scene.items():
        if isinstance(value, dict):
            lines += [f"[{key}]"] + [f"{k} = {toml_value(v)}" for k, v in value.items()] + [""]
        elif isinstance(value, list) and value and isinstance(value[0], dict):
            for item in value:
                lines += [f"[[{key}]]"] + [f"{k} = {toml_value(v)}" for k, v in item.items()] + [""]
        else:
            lines.insert(0, f"{key} = {toml_value(value)}")
    return "\n".join(lines)


def psnr(image, target):
    peak = target.max()
    return 10 * math.log10(peak * peak / max(((image - target) ** 2).mean(), 1e-30))


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("scene", type=pathlib.Path, help="the scene file the capture was made from")
    parser.add_argument("capture", type=pathlib.Path, help="the capture's folder")
    parser.add_argument("--set", default="test", help="train, test or relit (transforms_SET.json)")
    parser.add_argument("--exr", action="store_true", help="the capture's exr/ images instead of the PNGs")
    parser.add_argument("--spp", type=int, default=1024, help="volgrad's samples per pixel")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--volgrad", default="target/release/volgrad")
    args = parser.parse_args()

    scene = tomllib.loads(args.scene.read_text())
    scene["medium"]["vdb"] = str((args.scene.parent / scene["medium"]["vdb"]).resolve())
    record = json.loads((args.capture / "capture.json").read_text())
    lights = record["relit_lights" if args.set == "relit" else "lights"]
    sky = np.sum([spectrum(l["radiance"]) for l in lights if l["type"] == "constant"] or [[0, 0, 0]], axis=0)
    root = args.capture / "exr" if args.exr else args.capture
    transforms = json.loads((root / f"transforms_{args.set}.json").read_text())
    fov_deg = math.degrees(transforms["camera_angle_x"])
    ratios, medium_ratios, scores = [], [], []
    with tempfile.TemporaryDirectory(prefix="capture-check-") as tmp:
        for i, frame in enumerate(transforms["frames"]):
            m = np.array(frame["transform_matrix"], dtype=np.float64)
            position, up, back = m[:3, 3], m[:3, 1], m[:3, 2]
            view = dict(scene)
            view["camera"] = {
                "position": position.tolist(),
                "target": (position - back).tolist(),
                "up": up.tolist(),
                "fov_deg": fov_deg,
                "width": transforms["w"],
                "height": transforms["h"],
            }
            view["light"] = lights
            scene_path = pathlib.Path(tmp) / f"view{i}.toml"
            scene_path.write_text(toml_text(view))
            exr = pathlib.Path(tmp) / f"view{i}.exr"
            run = subprocess.run(
                [args.volgrad, "render", str(scene_path), "--spp", str(args.spp), "--seed", str(args.seed),
                 "--quiet", "--output", str(exr)],
                stdout=subprocess.DEVNULL,
            )
            if run.returncode != 0:
                sys.exit(f"error: `{args.volgrad} render` failed (its message is above)")
            ours = read_rgba(exr)[..., :3]
            picture = read_rgba(root / frame["file_path"])
            target = picture[..., :3] + (1 - picture[..., 3:4]) * sky
            ratio = target.reshape(-1, 3).mean(axis=0) / ours.reshape(-1, 3).mean(axis=0)
            covered = picture[..., 3] > 0.05
            medium = target[covered].mean(axis=0) / ours[covered].mean(axis=0)
            score = psnr(ours, target)
            ratios.append(ratio)
            medium_ratios.append(medium)
            scores.append(score)
            print(
                f"{frame['file_path']}: capture/volgrad means {np.round(ratio, 4).tolist()}, "
                f"where alpha > 0.05 {np.round(medium, 4).tolist()}, PSNR {score:.2f} dB"
            )
    ratio, medium = np.mean(ratios, axis=0), np.mean(medium_ratios, axis=0)
    print(
        f"{args.set}: {len(scores)} views, mean ratio capture/volgrad (R, G, B) = "
        f"{', '.join(f'{r:.4f}' for r in ratio)}, where alpha > 0.05 {', '.join(f'{r:.4f}' for r in medium)}; "
        f"PSNR {np.mean(scores):.2f} dB (volgrad {args.spp} spp)"
    )


if __name__ == "__main__":
    main()
