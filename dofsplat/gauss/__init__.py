"""The stages that draw a 3D Gaussian Splatting scene (``dofsplat.gaussians.Gaussians``).

A Gaussian scene is drawn as its trainers draw it (Kerbl et al. 2023; gsplat is the
yardstick), through the same camera and lens as surfels:

    project (EWA volume-splatting Jacobian, view-angle clamp, 0.3 px^2 low-pass; the lens's
    blur) -> colour (spherical harmonics for the view direction) -> sort by depth and bin
    to 16 x 16 tiles -> composite front to back per pixel (alpha <= 0.999, below 1/255
    skipped, stop at transmittance 1e-4)

``sh``: the spherical-harmonic colour; ``project``: the 2-D footprints; ``composite``: the
tiles and the front-to-back blend; ``slow``: their numpy twins. The pipeline that calls them
in order is ``dofsplat.backends.cpu_gauss.render_gaussians_cpu``.
"""
