#!/usr/bin/env python3
"""An independent forward reference for emission: renders a volgrad scene with Blender's Cycles
(`pip install bpy==4.2.0`, Blender as a Python module, for Python 3.11) and with volgrad, several
passes each with their own seeds, and compares the image means as `mitsuba_reference.py` does.

    cargo build --release
    python3 scripts/cycles_reference.py scenes/inverse/flame-scene.toml --spp 64 --passes 8
    python3 scripts/cycles_reference.py scenes/fire.toml --kelvin 800 3100 --spp 16 --passes 8

Cycles reads the VDB file itself. What the script maps:

- camera: perspective, horizontal field of view, placed by volgrad's look-at; a box pixel filter
  one pixel wide; no denoising, adaptive sampling or clamping;
- `constant` → the world's background colour; `directional` → a sun lamp of angle 0 whose
  strength is the irradiance (Cycles' sun strength is W/m² on a surface facing it);
- the medium: a volume object with volgrad's density grid, full precision and no clipping, and a
  node material: σt = density_scale × `density`, `Volume Absorption` and `Volume Scatter` (its
  Henyey-Greenstein g) with colour = the albedo (a constant or the albedo grid's attribute), so
  that σa = (1 − α)·σt and σs = α·σt;
- emission: an `Emission` shader of colour (1 − α)·Le and strength σt. Cycles' volume emission is
  radiance per unit length, so this is volgrad's σa·Le. Le is `radiance = [r, g, b]` × the grid
  value, or for a blackbody, strength × volgrad's normalised blackbody (pbrt-v4's) at
  T = (value − offset)·scale, 0 at or below the cutoff. Cycles' own Blackbody node normalises
  otherwise, so the colour is volgrad's formula evaluated in numpy (`blackbody_ramp.py`) and put
  into the node tree as a 32-stop table over 1/T; `--kelvin LO HI` gives the temperatures the grid
  holds (T is clamped to them) and the script prints the table's largest error there;
- depth: volgrad's max_depth counts scattering events. Cycles' bounces count the indirect ones:
  light reached from the first scattering (the sun's, or emission further along) is direct, its
  bounce 0. So Cycles' volume bounces are volgrad's max_depth − 1, and max_depth 0 (only the
  emission along the camera's rays) has no counterpart.

Cycles marches through heterogeneous volumes in steps (`--step-rate` voxels per step, 0.05 by
default; 0.2 and 0.02 gave the same means). Cycles' light tree is turned off: it undersamples a
sun inside a dense volume. Cycles' volume reaches on to where its interpolation falls to 0, a voxel
beyond the outermost active voxel, where volgrad's medium ends half a voxel out: a grid not yet 0
at its edge shows a difference at its rim (docs/validation.md, "Against Blender's Cycles:
emission").
"""

import math
import sys

import numpy as np

from reference_compare import arguments, compare_passes, resolved, spectrum


def look_at(position, target, up):
    """The camera's world matrix: Blender cameras look down their −Z with +Y up."""
    import mathutils

    p, t, u = (mathutils.Vector(v) for v in (position, target, up))
    forward = (t - p).normalized()
    right = forward.cross(u).normalized()
    true_up = right.cross(forward)
    m = mathutils.Matrix.Identity(4)
    for row in range(3):
        m[row][0], m[row][1], m[row][2], m[row][3] = right[row], true_up[row], -forward[row], p[row]
    return m


def blackbody_radiance(nodes, links, math_node, value, emission, kelvin):
    """Le = strength × the normalised blackbody at T = (value − offset)·scale, 0 at or below the
    cutoff, through `blackbody_ramp`'s table over `kelvin` = (lo, hi); T is clamped to that range."""
    from blackbody_ramp import STOPS, XYZ_TO_SRGB, ramp

    blackbody = emission["blackbody"]
    lo, hi = kelvin
    t = math_node(
        "MULTIPLY",
        math_node("SUBTRACT", value, float(blackbody.get("offset", 0.0))),
        float(blackbody.get("scale", 1.0)),
    )
    lit = math_node("GREATER_THAN", t, max(float(blackbody.get("cutoff", 0.0)), 0.0))
    t = math_node("MINIMUM", math_node("MAXIMUM", t, lo), hi)
    fac = math_node("MULTIPLY", math_node("SUBTRACT", math_node("DIVIDE", 1.0, t), 1.0 / hi), 1.0 / (1.0 / lo - 1.0 / hi))
    positions, values, offset, span = ramp(lo, hi)
    table = nodes.new("ShaderNodeValToRGB")
    links.new(fac, table.inputs["Fac"])
    stops = table.color_ramp
    stops.interpolation = "LINEAR"
    # Set each stop as it is made: a new stop re-sorts the list.
    stops.elements[0].position, stops.elements[0].color = 0.0, (*values[0], 1.0)
    stops.elements[1].position, stops.elements[1].color = 1.0, (*values[-1], 1.0)
    for position, v in zip(positions[1:-1], values[1:-1]):
        stops.elements.new(position).color = (*v, 1.0)
    assert len(stops.elements) == STOPS
    channels = nodes.new("ShaderNodeSeparateColor")
    links.new(table.outputs["Color"], channels.inputs["Color"])
    t_minus_5 = math_node("POWER", t, -5.0)
    xyz = nodes.new("ShaderNodeCombineXYZ")
    for c, name in enumerate(("Red", "Green", "Blue")):
        log = math_node("ADD", math_node("MULTIPLY", channels.outputs[name], float(span[c])), float(offset[c]))
        links.new(math_node("MULTIPLY", math_node("EXPONENT", log, 0.0), t_minus_5), xyz.inputs[c])
    rgb = nodes.new("ShaderNodeCombineXYZ")
    strength = float(emission.get("strength", 1.0))
    for c, row in enumerate(XYZ_TO_SRGB):
        dot = nodes.new("ShaderNodeVectorMath")
        dot.operation = "DOT_PRODUCT"
        links.new(xyz.outputs[0], dot.inputs[0])
        dot.inputs[1].default_value = [float(r) for r in row]
        channel = math_node("MULTIPLY", math_node("MAXIMUM", dot.outputs["Value"], 0.0), strength)
        links.new(math_node("MULTIPLY", channel, lit), rgb.inputs[c])
    return rgb.outputs[0]


def node_material(bpy, medium, emission, kelvin):
    """The medium's volume shader; see the module doc for what each node is."""
    material = bpy.data.materials.new("medium")
    material.use_nodes = True
    tree = material.node_tree
    tree.nodes.clear()
    nodes, links = tree.nodes, tree.links

    def math_node(operation, a, b):
        node = nodes.new("ShaderNodeMath")
        node.operation = operation
        for socket, value in zip(node.inputs, (a, b)):
            if isinstance(value, (int, float)):
                socket.default_value = value
            else:
                links.new(value, socket)
        return node.outputs[0]

    def attribute(name):
        node = nodes.new("ShaderNodeAttribute")
        node.attribute_type = "GEOMETRY"
        node.attribute_name = name
        return node

    density = attribute(medium.get("grid", "density")).outputs["Fac"]
    sigma_t = math_node("MULTIPLY", density, float(medium.get("density_scale", 1.0)))
    albedo = medium.get("albedo", 1.0)
    if isinstance(albedo, dict):
        albedo_colour = attribute(albedo["grid"]).outputs["Color"]
    else:
        rgb = nodes.new("ShaderNodeRGB")
        rgb.outputs[0].default_value = (*spectrum(albedo), 1.0)
        albedo_colour = rgb.outputs[0]
    absorption = nodes.new("ShaderNodeVolumeAbsorption")
    scatter = nodes.new("ShaderNodeVolumeScatter")
    scatter.inputs["Anisotropy"].default_value = float(medium.get("phase_g", 0.0))
    for shader in (absorption, scatter):
        links.new(albedo_colour, shader.inputs["Color"])
        links.new(sigma_t, shader.inputs["Density"])
    total = nodes.new("ShaderNodeAddShader")
    links.new(absorption.outputs[0], total.inputs[0])
    links.new(scatter.outputs[0], total.inputs[1])
    volume = total.outputs[0]
    if emission is not None:
        # Colour (1 − α)·Le, strength σt: σa·Le per unit length.
        one_minus = nodes.new("ShaderNodeVectorMath")
        one_minus.operation = "SUBTRACT"
        one_minus.inputs[0].default_value = (1.0, 1.0, 1.0)
        links.new(albedo_colour, one_minus.inputs[1])
        colour = nodes.new("ShaderNodeVectorMath")
        colour.operation = "MULTIPLY"
        links.new(one_minus.outputs[0], colour.inputs[0])
        value = attribute(emission["grid"]).outputs["Fac"]
        if "radiance" in emission:
            le = nodes.new("ShaderNodeVectorMath")
            le.operation = "SCALE"
            le.inputs[0].default_value = spectrum(emission["radiance"])
            links.new(value, le.inputs["Scale"])
            links.new(le.outputs[0], colour.inputs[1])
        else:
            links.new(blackbody_radiance(nodes, links, math_node, value, emission, kelvin), colour.inputs[1])
        glow = nodes.new("ShaderNodeEmission")
        links.new(colour.outputs[0], glow.inputs["Color"])
        links.new(sigma_t, glow.inputs["Strength"])
        with_glow = nodes.new("ShaderNodeAddShader")
        links.new(volume, with_glow.inputs[0])
        links.new(glow.outputs[0], with_glow.inputs[1])
        volume = with_glow.outputs[0]
    output = nodes.new("ShaderNodeOutputMaterial")
    links.new(volume, output.inputs["Volume"])
    return material


def cycles_lights(bpy, blender, lights):
    """A scene file's `[[light]]` list as Blender's world and sun lamps, replacing any the scene
    has: `constant` lights summed into the world's background colour, each `directional` one a sun
    lamp of angle 0 whose strength is its irradiance."""
    import mathutils

    for lamp in [o for o in blender.objects if o.type == "LIGHT"]:
        bpy.data.objects.remove(lamp)
    world = bpy.data.worlds.new("world")
    world.use_nodes = True
    background = world.node_tree.nodes["Background"]
    background.inputs["Strength"].default_value = 1.0
    sky = [0.0, 0.0, 0.0]
    for i, light in enumerate(lights):
        if light["type"] == "constant":
            sky = [a + b for a, b in zip(sky, spectrum(light["radiance"]))]
        elif light["type"] == "directional":
            irradiance = spectrum(light["irradiance"])
            strength = max(irradiance)
            sun = bpy.data.lights.new(f"sun{i}", "SUN")
            sun.energy = strength
            sun.color = [c / strength for c in irradiance] if strength > 0 else [1.0, 1.0, 1.0]
            sun.angle = 0.0
            lamp = bpy.data.objects.new(f"sun{i}", sun)
            # A sun shines down its −Z.
            direction = mathutils.Vector(light["direction"]).normalized()
            lamp.rotation_mode = "QUATERNION"
            lamp.rotation_quaternion = direction.to_track_quat("-Z", "Y")
            blender.collection.objects.link(lamp)
        else:
            sys.exit(f"error: light {i}: only constant and directional lights are mapped")
    background.inputs["Color"].default_value = (*sky, 1.0)
    blender.world = world


def cycles_scene(bpy, scene_path, scene, max_depth, step_rate, kelvin):
    """Sets up Blender's scene for `scene` (parsed TOML of the file at `scene_path`)."""
    import mathutils

    bpy.ops.wm.read_factory_settings(use_empty=True)
    blender = bpy.context.scene
    camera, medium = scene["camera"], scene["medium"]
    emission = medium.get("emission")
    if emission is not None and "blackbody" in emission and kelvin is None:
        sys.exit("error: a blackbody needs --kelvin LO HI, the temperatures its grid holds (the colour table spans them)")
    albedo = medium.get("albedo")
    if "vdb" in (emission or {}) or (isinstance(albedo, dict) and "vdb" in albedo):
        sys.exit("error: grids from other files are not mapped; keep them in medium.vdb")
    if "grid_index" in medium or "levelset" in medium:
        sys.exit("error: name the density grid with medium.grid (grid_index and level sets are not mapped)")
    if medium.get("filter", "trilinear") != "trilinear":
        sys.exit("error: Cycles interpolates trilinearly; the scene's filter must be too")

    volume = bpy.data.volumes.new("medium")
    volume.filepath = str((scene_path.parent / medium["vdb"]).resolve())
    volume.render.precision = "FULL"
    volume.render.clipping = 0.0
    volume.materials.append(node_material(bpy, medium, emission, kelvin))
    medium_object = bpy.data.objects.new("medium", volume)
    volume.grids.load()
    names = [grid.name for grid in volume.grids]
    wanted = [medium.get("grid", "density")] + [
        g["grid"] for g in (albedo, emission) if isinstance(g, dict)
    ]
    if missing := [name for name in wanted if name not in names]:
        sys.exit(f"error: {volume.filepath} has no grid {missing[0]!r} (it has {names})")
    # Cycles samples voxel i's value at index i + ½ (a texel's centre), where OpenVDB and volgrad
    # put it at i: the object is moved back by half a voxel along the grids' axes.
    voxel_axes = {tuple(map(tuple, volume.grids[names.index(n)].matrix_object.to_3x3())) for n in wanted}
    if len(voxel_axes) > 1:
        sys.exit("error: the grids' voxels differ in size or orientation; the half-voxel shift needs one")
    index_to_object = volume.grids[names.index(wanted[0])].matrix_object
    half_voxel = index_to_object.to_3x3() @ mathutils.Vector((0.5, 0.5, 0.5))
    medium_object.matrix_world = mathutils.Matrix.Translation(-half_voxel)
    blender.collection.objects.link(medium_object)

    lens = bpy.data.cameras.new("camera")
    lens.sensor_fit = "HORIZONTAL"
    lens.angle = math.radians(camera["fov_deg"])
    lens.clip_start, lens.clip_end = 1e-3, 1e9
    eye = bpy.data.objects.new("camera", lens)
    eye.matrix_world = look_at(camera["position"], camera["target"], camera.get("up", [0, 1, 0]))
    blender.collection.objects.link(eye)
    blender.camera = eye

    cycles_lights(bpy, blender, scene.get("light", []))

    blender.render.engine = "CYCLES"
    blender.render.resolution_x, blender.render.resolution_y = camera["width"], camera["height"]
    blender.render.resolution_percentage = 100
    blender.render.image_settings.file_format = "OPEN_EXR"
    blender.render.image_settings.color_depth = "32"
    blender.render.image_settings.color_mode = "RGB"
    blender.view_settings.view_transform = "Standard"
    cycles = blender.cycles
    cycles.device = "CPU"
    cycles.use_denoising = False
    cycles.use_adaptive_sampling = False
    cycles.sample_clamp_direct = cycles.sample_clamp_indirect = 0.0
    cycles.pixel_filter_type = "BOX"
    cycles.filter_width = 1.0
    cycles.max_bounces = cycles.volume_bounces = max_depth - 1
    cycles.transparent_max_bounces = cycles.transmission_bounces = 1024
    cycles.min_light_bounces = cycles.min_transparent_bounces = 0
    cycles.volume_step_rate = step_rate
    cycles.volume_max_steps = 1 << 20
    # Cycles 4.2's light tree undersamples a sun inside a dense volume (2.4 % dark on the
    # coloured smoke lit by its sun alone, where Mitsuba 3 and volgrad agree); without it, and
    # without the threshold below which it drops light samples, its light sampling is plain.
    cycles.use_light_tree = False
    cycles.light_sampling_threshold = 0.0
    return blender


def read_exr(bpy, path):
    """An EXR as rows top to bottom × columns × RGB (Blender keeps images bottom-up)."""
    image = bpy.data.images.load(str(path))
    w, h = image.size
    pixels = np.array(image.pixels[:], dtype=np.float64).reshape(h, w, image.channels)[::-1, :, :3]
    bpy.data.images.remove(image)
    return pixels


def main():
    parser = arguments(__doc__.split("\n\n")[0])
    parser.add_argument("--step-rate", type=float, default=0.05, help="Cycles' step, in voxels")
    parser.add_argument("--kelvin", type=float, nargs=2, metavar=("LO", "HI"), help="a blackbody's range")
    args, scene, out, max_depth = resolved(parser, "cycles")
    if args.kelvin is not None:
        from blackbody_ramp import ramp_error

        lo, hi = args.kelvin
        if not 0 < lo < hi:
            sys.exit("error: --kelvin needs 0 < LO < HI")
        print(f"blackbody table over {lo:g}–{hi:g} K: at most {100 * ramp_error(lo, hi):.3f} % from the formula")
    if max_depth < 1:
        sys.exit("error: --max-depth must be at least 1 (Cycles lights the first scattering at bounce 0)")

    import bpy

    blender = cycles_scene(bpy, args.scene, scene, max_depth, args.step_rate, args.kelvin)
    blender.cycles.samples = args.spp

    def render(seed, exr):
        blender.cycles.seed = seed
        blender.render.filepath = str(exr)
        bpy.ops.render.render(write_still=True)

    compare_passes(args, out, max_depth, "cycles", render, lambda exr: read_exr(bpy, exr))


if __name__ == "__main__":
    main()
