"""volgrad: differentiable volume rendering of OpenVDB grids, from Python.

Grids are numpy arrays: ``read_grid`` and ``write_grid`` read and write OpenVDB files (no
pyopenvdb needed). A ``Scene`` is a scene file loaded (``Scene.load``) or built from a density array
and the medium's constants (``Scene.from_parts``); ``Scene.render`` gives linear images and
``Scene.grad`` the vector-Jacobian product of a render: Σ over pixels of adjoint · ∂image/∂θ, with
the joint (sample-matching), DRT or naive estimator. ``volgrad.torch`` wraps both as a PyTorch
autograd function, ``volgrad.jax`` as a JAX function with a custom VJP. Every call releases the
GIL and runs on all cores (``threads=`` limits it); Ctrl-C raises ``KeyboardInterrupt``. The
manual's page is docs/python.md.
"""

from volgrad._volgrad import Camera, Scene, read_grid, write_grid

__all__ = ["Camera", "Scene", "read_grid", "write_grid"]
