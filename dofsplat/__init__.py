"""dofsplat: depth of field for point clouds by EWA surface splatting.

An implementation of Krivanek & Zara, "Rendering Depth-of-Field with Surface Splatting"
(2003). Importing the package is cheap: numba kernels compile on first render.
"""

__version__ = "0.1.0"  # first: dofsplat.jit names its kernel cache after it

from .camera import Camera, EyeLens, ThinLens, photographic
from .errors import DofsplatError
from .frame import RenderResult, RenderSettings
from .metrics import compare
from .render import focus_distance_at, render
from .reference import render_reference
from .sequence import Keyframe, animate
from .viewer import view
from .shading import HEADLIGHT, Light
from .surfels import Material, Surfels
from .gaussians import Gaussians


__all__ = [
    "Camera", "EyeLens", "ThinLens", "photographic", "DofsplatError", "RenderResult",
    "RenderSettings", "focus_distance_at", "render", "HEADLIGHT", "Light", "Material",
    "Surfels", "Gaussians", "__version__", "compare", "render_reference", "Keyframe", "animate", "view",
]
