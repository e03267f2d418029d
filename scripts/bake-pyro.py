#!/usr/bin/env python3
"""Bakes `scenes/assets/mantaflow_fire.vdb`: a small fire-and-smoke simulation by Blender's
Mantaflow solver (Blender 4.5 LTS as a Python module), written as OpenVDB files, one per frame.

    python3 -m venv /tmp/bpy && /tmp/bpy/bin/pip install bpy==4.5.15
    /tmp/bpy/bin/python scripts/bake-pyro.py /tmp/pyro      # about 30 s on one core
    cp /tmp/pyro/data/fluid_data_0040.vdb scenes/assets/mantaflow_fire.vdb

The scene: a 4 m cube domain (gas, 56 voxels along each edge, no noise upres), a sphere of radius
0.35 m near its floor that emits fuel and smoke (flow type "both", inflow), 40 frames at Blender's
defaults otherwise. Each frame's file holds float grids `density` (smoke), `flame` (fire, 0..1) and
`temperature` (Mantaflow's heat, 0..`flame_max_temp` = 3), a `velocity` vec3 grid and a constant
`shadow` grid, as half floats (Blender's default). Mantaflow stores them in the domain's own frame:
index 0..55 maps to 0..4 m, z up. Two bakes here gave the same active voxels and value ranges.
"""
import ctypes
import glob
import os
import sys
import types

import bpy

FRAMES = 40


def fix_mantaflow_types():
    """Blender as a Python module builds the `manta` module at `import bpy`, before Mantaflow's
    `WrapperRegistry::construct()` has copied each parent class's methods into its subclasses, so
    every solver script fails (`'LevelsetGrid' object has no attribute 'setConst'`, then
    `Manta::Error: can't clean grid cache`; princeton-vl/infinigen#318). The Blender program loads
    `manta` only after that copy. So stand a module in for `manta` that, at Mantaflow's first
    `from manta import *` (which runs right after the copy), builds the module again through the
    exported `PyInit_manta_main`, whose types then carry their inherited methods."""
    so = next(hit for p in sys.path for hit in glob.glob(os.path.join(p or ".", "bpy", "__init__*.so")))
    init = ctypes.PyDLL(so).PyInit_manta_main
    init.restype = ctypes.py_object
    init.argtypes = []

    class LazyManta(types.ModuleType):
        def __getattr__(self, name):
            if name.startswith("__") and name != "__all__":
                raise AttributeError(name)
            if "_rebuilt" not in self.__dict__:
                rebuilt = init()
                for key, value in rebuilt.__dict__.items():
                    if key not in ("__name__", "__loader__", "__spec__", "__package__"):
                        self.__dict__[key] = value
                self.__dict__["_rebuilt"] = True
                self.__dict__["__all__"] = [k for k in rebuilt.__dict__ if not k.startswith("_")]
                if name in self.__dict__:
                    return self.__dict__[name]
            raise AttributeError(name)

    sys.modules["manta"] = LazyManta("manta")


def build_scene(cache):
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    scene.frame_start, scene.frame_end = 1, FRAMES

    bpy.ops.mesh.primitive_cube_add(size=4.0, location=(0, 0, 2))
    domain = bpy.context.active_object
    settings = domain.modifiers.new("Fluid", "FLUID")
    settings.fluid_type = "DOMAIN"
    d = settings.domain_settings
    d.domain_type = "GAS"
    d.resolution_max = 56
    d.use_noise = False
    d.cache_type = "ALL"
    d.cache_data_format = "OPENVDB"
    d.openvdb_cache_compress_type = "ZIP"  # Debian's OpenVDB reads zip; blosc is optional there
    d.cache_directory = cache
    d.cache_frame_start, d.cache_frame_end = 1, FRAMES

    bpy.ops.mesh.primitive_uv_sphere_add(radius=0.35, location=(0, 0, 0.5))
    flow = bpy.context.active_object.modifiers.new("Fluid", "FLUID")
    flow.fluid_type = "FLOW"
    f = flow.flow_settings
    f.flow_type = "BOTH"
    f.flow_behavior = "INFLOW"
    f.flow_source = "MESH"
    f.use_plane_init = False
    f.fuel_amount = 1.0
    f.temperature = 1.0
    return scene, domain


def main():
    if len(sys.argv) != 2:
        sys.exit("usage: bake-pyro.py CACHE_DIR")
    cache = os.path.abspath(sys.argv[1])
    fix_mantaflow_types()
    scene, domain = build_scene(cache)
    bpy.ops.object.select_all(action="DESELECT")
    domain.select_set(True)
    bpy.context.view_layer.objects.active = domain
    context = dict(active_object=domain, object=domain, selected_objects=[domain],
                   selected_editable_objects=[domain], scene=scene)
    with bpy.context.temp_override(**context):
        result = bpy.ops.fluid.bake_all()
    files = sorted(glob.glob(os.path.join(cache, "data", "*.vdb")))
    print(f"bake: {result}, {len(files)} files in {cache}/data", flush=True)
    sys.stdout.flush()
    # Mantaflow's grid cache aborts in Python's teardown (the same missing-method state); every
    # file is written by now, so leave without it.
    os._exit(0 if len(files) == FRAMES else 1)


main()
