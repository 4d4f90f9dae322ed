"""Rendering a frame (paper Sections 4-6): the one public entry point, ``render``.

    select (LOD cut) -> shade -> project (EWA kernel + DOF blur) -> bin to tiles ->
    rasterise into the A-buffer and resolve (surface reconstruction, compositing)

``render`` dispatches the frame to a backend: ``backends.cpu`` (numba, the default) or
``backends.cuda`` (numba-cuda), the same stages from the same per-splat maths. The settings,
the result and the per-frame parameters live in ``dofsplat.frame``, below both backends;
they, and the CPU stages, are importable from here too.
"""

from __future__ import annotations

import math
import numbers

from .backends.cpu import (plan_bands, project, rasterize, render_cpu, select,
                           shade_surfels, warm_up)
from .camera import Camera, EyeLens, ThinLens
from .errors import DofsplatError
from .frame import (LOD_PALETTE, RECONSTRUCTIONS, RenderResult, RenderSettings,
                    aperture_shape, coc_coefficients, frame_arguments, kernel_floor,
                    lod_level_colors, lod_tree, merge_parameters)
from .gaussians import Gaussians
from .surfels import Surfels

__all__ = [
    "render", "focus_distance_at", "render_cpu", "select", "shade_surfels", "project",
    "plan_bands", "rasterize", "warm_up", "RenderSettings", "RenderResult", "RECONSTRUCTIONS",
    "LOD_PALETTE", "aperture_shape", "coc_coefficients", "kernel_floor", "lod_level_colors",
    "lod_tree", "merge_parameters",
]


def render(surfels: Surfels | Gaussians, camera: Camera,
           lens: ThinLens | EyeLens | None = None, settings: RenderSettings | None = None,
           hierarchy=None) -> RenderResult:
    """Render surfels with depth of field (paper Sections 4-6), or a 3D Gaussian Splatting
    scene as its trainers draw it, through the same lens (``dofsplat.gauss``).

    surfels:   the model (``Surfels``, or ``Gaussians``)
    camera:    view, projection and image size (``Camera``)
    lens:      ``ThinLens`` or ``EyeLens``; None, or an aperture of 0, is a pinhole
    settings:  ``RenderSettings`` (cutoff, shading, background, LOD, ...)
    hierarchy: the model's ``dofsplat.lod.Hierarchy`` when ``settings.lod``; built on first
               use and kept on the ``Surfels`` object if not given
    """
    settings = frame_arguments("render()", surfels, camera, lens, settings, hierarchy)
    from .backends import resolve_device

    if isinstance(surfels, Gaussians):
        if hierarchy is not None:
            raise DofsplatError("render(): a Gaussian scene takes no surfel hierarchy")
        if resolve_device(settings.device) == "cuda":
            from .backends.cuda_gauss import render_gaussians_cuda

            return render_gaussians_cuda(surfels, camera, lens, settings)  # the same stages, on the GPU
        from .backends.cpu_gauss import render_gaussians_cpu

        return render_gaussians_cpu(surfels, camera, lens, settings)

    if resolve_device(settings.device) == "cuda":
        from .backends.cuda import render_cuda

        return render_cuda(surfels, camera, lens, settings, hierarchy)  # the same stages, on the GPU
    return render_cpu(surfels, camera, lens, settings, hierarchy)


def focus_distance_at(surfels: Surfels, camera: Camera, x: float, y: float,
                      settings: RenderSettings | None = None) -> float:
    """Depth of the surface seen at pixel position (x, y) in a pinhole render: for autofocus."""
    settings = frame_arguments("focus_distance_at()", surfels, camera, None, settings)
    if not all(isinstance(v, numbers.Real) for v in (x, y)):
        raise DofsplatError(f"focus_distance_at(): x and y must be numbers (a pixel position), "
                            f"got {x!r}, {y!r}")
    if not (0 <= x < camera.width and 0 <= y < camera.height):
        raise DofsplatError(f"focus pixel ({x:g}, {y:g}) lies outside the {camera.width}x{camera.height} image")
    pinhole = render(surfels, camera, None, settings)
    d = float(pinhole.depth[int(y), int(x)])
    if not math.isfinite(d):
        raise DofsplatError(f"no surface is seen at pixel ({x:g}, {y:g}) to focus on")
    return d
