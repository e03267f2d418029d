"""Type stubs for volgrad (the Rust extension volgrad._volgrad and its re-exports)."""

from os import PathLike
from typing import Any, Dict, List, Optional, Sequence, Tuple, Union

import numpy as np
import numpy.typing as npt

_Path = Union[str, PathLike[str]]
_F32 = npt.NDArray[np.float32]
_F64 = npt.NDArray[np.float64]

def read_grid(path: _Path, name: Optional[str] = None) -> Tuple[_F32, _F64]:
    """The active box of a float grid: (values (nx, ny, nz), 4×4 index_to_world of the array)."""

def read_picture(
    path: _Path, color_space: Optional[str] = None
) -> Tuple[_F32, Optional[_F32]]:
    """A picture as linear radiance (H, W, 3), premultiplied by alpha, and alpha (H, W) or None."""

def write_grid(
    path: _Path,
    array: _F32,
    index_to_world: _F64,
    name: str = "density",
    overwrite: bool = False,
    half: bool = False,
) -> None:
    """Writes ``array`` as a sparse float grid (only 8³ bricks holding non-zero values)."""

class Camera:
    """A pinhole camera: look-at and horizontal field of view, or full intrinsics in pixels."""

    def __init__(
        self,
        position: Sequence[float],
        target: Sequence[float],
        up: Sequence[float] = (0.0, 1.0, 0.0),
        fov_deg: Optional[float] = None,
        width: int = 64,
        height: int = 64,
        fx: Optional[float] = None,
        fy: Optional[float] = None,
        cx: Optional[float] = None,
        cy: Optional[float] = None,
    ) -> None: ...
    @staticmethod
    def from_transforms(path: _Path) -> List["Camera"]:
        """The cameras of a NeRF / instant-ngp transforms.json, in frame order."""
    @staticmethod
    def from_colmap(model: _Path, images: Optional[_Path] = None) -> List["Camera"]:
        """The cameras of a COLMAP text model (cameras.txt, images.txt)."""
    @staticmethod
    def orbit(
        count: int,
        distance: float,
        centre: Sequence[float] = (0.0, 0.0, 0.0),
        elevation_deg: Tuple[float, float] = (-30.0, 70.0),
        fov_deg: float = 40.0,
        width: int = 64,
        height: int = 64,
        azimuth_offset_deg: float = 0.0,
        up: Sequence[float] = (0.0, 1.0, 0.0),
    ) -> List["Camera"]:
        """``count`` cameras on a Fibonacci spiral around ``centre`` (a run file's [views.orbit])."""
    @property
    def width(self) -> int: ...
    @property
    def height(self) -> int: ...
    @property
    def position(self) -> Tuple[float, float, float]: ...
    @property
    def intrinsics(self) -> Tuple[float, float, float, float]:
        """(fx, fy, cx, cy) in pixels."""

class Scene:
    """A scene ready to render and differentiate."""

    @staticmethod
    def load(path: _Path) -> "Scene":
        """Reads a scene file (TOML) with its grid and lights."""
    @staticmethod
    def from_parts(
        density: _F32,
        index_to_world: _F64,
        density_scale: float = 1.0,
        albedo: Union[float, Sequence[float], _F32, None] = None,
        phase_g: float = 0.0,
        lights: Optional[List[Dict[str, Any]]] = None,
        camera: Optional[Camera] = None,
        spp: Optional[int] = None,
        seed: Optional[int] = None,
        max_depth: Optional[int] = None,
        emission: Optional[_F32] = None,
        emission_kind: Optional[Dict[str, Any]] = None,
    ) -> "Scene":
        """A scene from a density array and the medium's constants; lights as scene-file tables;
        an emission array with what its values mean (a scene file's medium.emission keys)."""
    @property
    def density(self) -> Tuple[_F32, _F64]:
        """(values (nx, ny, nz), 4×4 index_to_world of the array's indices)."""
    def set_density(self, density: _F32, index_to_world: Optional[_F64] = None) -> None: ...
    @property
    def camera(self) -> Optional[Camera]:
        """The scene's own camera; None for ``from_parts`` without ``camera``."""
    def render(
        self,
        cameras: Union[Camera, Sequence[Camera], None] = None,
        spp: Optional[int] = None,
        seed: Optional[int] = None,
        max_depth: Optional[int] = None,
        threads: Optional[int] = None,
        density: Optional[_F32] = None,
        albedo: Optional[_F32] = None,
        emission: Optional[_F32] = None,
    ) -> _F32:
        """(H, W, 3) for the scene's camera or one camera, (N, H, W, 3) for a list: linear
        radiance. View i of a list draws from seed + i·0x9E3779B97F4A7C15 (mod 2⁶⁴)."""
    def grad(
        self,
        adjoint: _F32,
        cameras: Union[Camera, Sequence[Camera], None] = None,
        estimator: str = "joint",
        parameter: str = "extinction",
        spp: Optional[int] = None,
        seed: Optional[int] = None,
        max_depth: Optional[int] = None,
        threads: Optional[int] = None,
        density: Optional[_F32] = None,
        albedo: Optional[_F32] = None,
        emission: Optional[_F32] = None,
    ) -> _F32:
        """Σ over pixels of adjoint · ∂image/∂θ, shaped like the parameter."""
