"""Checks docs/blender.md's recipe in Blender itself: imports a gradient VDB, builds the material the
recipe's table describes, renders it with Cycles and counts the red (positive), blue (negative) and
lit pixels of the picture, so that a recipe that shows nothing, or one colour only, is seen.

    /tmp/bpy/bin/python scripts/blender-gradient.py GRAD.vdb G OUT.png [--grid grad_density] [--density 5]

Blender as a Python module: python3 -m venv /tmp/bpy && /tmp/bpy/bin/pip install bpy==4.2.0.
G is the scale of step 2 of the recipe (the larger of |min| and |max|, from `vdb_print -l`).
"""

import argparse
import math

import bpy
from mathutils import Vector


def material(grid, g, d):
    """The recipe's node table, row by row."""
    mat = bpy.data.materials.new("gradient")
    mat.use_nodes = True
    nodes, links = mat.node_tree.nodes, mat.node_tree.links
    nodes.clear()
    out = nodes.new("ShaderNodeOutputMaterial")
    volume = nodes.new("ShaderNodeVolumePrincipled")
    volume.inputs["Color"].default_value = (0, 0, 0, 1)
    # Its Density is multiplied by the grid its Density Attribute names ("density" by default,
    # which a gradient file does not have): empty, the Density input alone counts.
    volume.inputs["Density Attribute"].default_value = ""
    attribute = nodes.new("ShaderNodeAttribute")
    attribute.attribute_type = "GEOMETRY"
    attribute.attribute_name = grid
    map_range = nodes.new("ShaderNodeMapRange")
    map_range.data_type, map_range.interpolation_type, map_range.clamp = "FLOAT", "LINEAR", True
    for name, value in [("From Min", -g), ("From Max", g), ("To Min", 0.0), ("To Max", 1.0)]:
        map_range.inputs[name].default_value = value
    ramp = nodes.new("ShaderNodeValToRGB")
    stops = ramp.color_ramp.elements
    stops[0].position, stops[0].color = 0.0, (0, 0, 1, 1)
    stops[1].position, stops[1].color = 1.0, (1, 0, 0, 1)
    stops.new(0.5).color = (1, 1, 1, 1)
    absolute = nodes.new("ShaderNodeMath")
    absolute.operation = "ABSOLUTE"
    scale = nodes.new("ShaderNodeMath")
    scale.operation = "MULTIPLY"
    scale.inputs[1].default_value = d / g
    links.new(attribute.outputs["Fac"], map_range.inputs["Value"])
    links.new(attribute.outputs["Fac"], absolute.inputs[0])
    links.new(map_range.outputs["Result"], ramp.inputs["Fac"])
    links.new(ramp.outputs["Color"], volume.inputs["Emission Color"])
    links.new(absolute.outputs["Value"], scale.inputs[0])
    links.new(scale.outputs["Value"], volume.inputs["Density"])
    links.new(scale.outputs["Value"], volume.inputs["Emission Strength"])
    links.new(volume.outputs["Volume"], out.inputs["Volume"])
    return mat


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("vdb")
    parser.add_argument("g", type=float)
    parser.add_argument("out")
    parser.add_argument("--grid", default="grad_density")
    parser.add_argument("--density", type=float, default=5.0)
    args = parser.parse_args()

    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    bpy.ops.object.volume_import(filepath=args.vdb)
    volume = bpy.context.active_object
    # Cycles treats voxels below the volume's Clipping (0.001) as empty space: a gradient's values
    # are far smaller, so nothing would render.
    volume.data.render.clipping = 0.0
    volume.data.materials.append(material(args.grid, args.g, args.density))
    corners = [volume.matrix_world @ Vector(c) for c in volume.bound_box]
    centre = sum(corners, Vector()) / 8
    size = max((max(c[i] for c in corners) - min(c[i] for c in corners)) for i in range(3))

    camera = bpy.data.objects.new("camera", bpy.data.cameras.new("camera"))
    scene.collection.objects.link(camera)
    camera.location = centre + Vector((0, -2.5 * size, 0.4 * size))
    camera.rotation_euler = (centre - camera.location).to_track_quat("-Z", "Y").to_euler()
    camera.data.angle = math.radians(40)
    scene.camera = camera
    scene.world = bpy.data.worlds.new("black")
    scene.world.color = (0, 0, 0)

    scene.render.engine = "CYCLES"
    scene.cycles.samples = 32
    scene.cycles.device = "CPU"
    scene.render.resolution_x = scene.render.resolution_y = 128
    scene.render.image_settings.file_format = "PNG"
    scene.render.filepath = args.out
    bpy.ops.render.render(write_still=True)

    pixels = bpy.data.images.load(args.out).pixels[:]
    rgb = [pixels[i : i + 3] for i in range(0, len(pixels), 4)]
    red = sum(1 for r, g, b in rgb if r > b + 0.05)
    blue = sum(1 for r, g, b in rgb if b > r + 0.05)
    lit = sum(1 for r, g, b in rgb if max(r, g, b) > 0.02)
    print(f"{args.out}: {lit} lit pixels of {len(rgb)}, {red} red (positive), {blue} blue (negative)")


if __name__ == "__main__":
    main()
