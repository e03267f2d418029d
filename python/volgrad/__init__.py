"""volgrad: differentiable volume rendering of OpenVDB grids, from Python.

Grids are numpy arrays: ``read_grid`` and ``write_grid`` read and write OpenVDB files (no
pyopenvdb needed); ``read_picture`` decodes a picture to linear radiance and alpha as a run file's
view set does. A ``Scene`` is a scene file loaded (``Scene.load``) or built from a density array
and the medium's constants (``Scene.from_parts``); ``Scene.render`` gives linear images and
``Scene.grad`` the vector-Jacobian product of a render: Σ over pixels of adjoint · ∂image/∂θ, with
the joint (sample-matching), DRT or naive estimator. ``volgrad.torch`` wraps both as a PyTorch
autograd function, ``volgrad.jax`` as a JAX function with a custom VJP (each imported when first
used, so that ``import volgrad`` imports neither PyTorch nor JAX). Every call releases the
GIL and runs on all cores (``threads=`` limits it); Ctrl-C raises ``KeyboardInterrupt``. The
manual's page is docs/python.md.
"""

import importlib

from volgrad._volgrad import Camera, Scene, read_grid, read_picture, write_grid

__all__ = ["Camera", "Scene", "read_grid", "read_picture", "write_grid"]


def __getattr__(name):
    # `volgrad.torch` and `volgrad.jax` after a plain `import volgrad`, as the manual writes them,
    # without importing PyTorch or JAX for users of neither.
    if name in ("torch", "jax"):
        return importlib.import_module(f"volgrad.{name}")
    raise AttributeError(f"module 'volgrad' has no attribute '{name}'")
