"""A peer: Gaussian-splat scenes drawn as gsplat 1.5.3 draws them, on the CPU (issue 48).

    pip install torch==2.13.0 && pip install gsplat==1.5.3 --no-deps   # the `gsplat-peer` extra
    python bench/gsplat_peer.py SCENE.ply --size 640x480 [--eye X Y Z --target X Y Z
        --up X Y Z --fov DEG] [--eps2d 0.3] [--antialiased] --out image.npz [--png image.png]

Neither torch nor gsplat is a dependency of dofsplat: this script is the yardstick that
dofsplat's own Gaussian renderer (``dofsplat.gauss``) is compared with, not part of it.
gsplat's fast path is CUDA only, so the image here is made of gsplat's pure-torch twins
(``gsplat.cuda._torch_impl``) and a port of its CUDA kernels where it has no twin:

  1. projection: ``_quat_scale_to_covar_preci`` (Sigma = R S S^T R^T),
     ``_fully_fused_projection`` (world to camera, the pinhole's Jacobian J evaluated at the
     centre clamped to 1.3x the field of view, ``cov2d = J Sigma J^T + eps2d I``, the conic,
     depth, and the antialiased mode's compensation sqrt(det cov2d / det(cov2d + eps2d I)));
     the footprint's half-widths come from ``_world_to_cam`` + ``_persp_proj`` with the CUDA
     kernel's opacity-aware extent (ProjectionEWA3DGSFused.cu, which the torch twin lacks):
     radius = ceil(min(3.33, sqrt(2 ln(o / (1/255)))) sqrt(cov2d_ii)), the Gaussian culled when
     o < 1/255, when its depth is outside (near_plane, far_plane) or its box misses the image.
  2. colour: ``_spherical_harmonics`` (Sloan's basis, 3DGS's signs) at the direction from the
     camera centre (inverse(viewmat)[:3, 3]) to the mean, then ``clamp_min(colour + 0.5, 0)``
     as gsplat/rendering.py does: clamped below only, never above 1.
  3. tiles (IntersectTile.cu): 16 x 16 px; a Gaussian joins the tiles
     [floor((m - r)/16), ceil((m + r)/16)) on each axis, clamped to the grid; the pairs are
     sorted by (tile, depth), stably (cub's radix sort of tile << 32 | float bits of depth).
  4. compositing (RasterizeToPixels3DGSFwd.cu), per pixel front to back, sampled at the pixel
     centre (j + 0.5, i + 0.5): sigma = 0.5 (a dx^2 + c dy^2) + b dx dy with the conic (a, b, c);
     alpha = min(0.999, o exp(-sigma)); skipped when sigma < 0 or alpha < 1/255;
     next_T = T (1 - alpha); when next_T <= 1e-4 the pixel stops and that Gaussian is NOT
     added; else C += alpha T colour, T = next_T. Image = C + T background, alpha = 1 - T.

Everything runs in float32 as on the GPU. The port agrees with gsplat's CUDA kernels up to
float rounding: CUDA's __expf is an approximation and its sums are in another order
(differences of order 1e-6 in a pixel, not a different image).

Camera: a dofsplat ``Camera`` (OpenGL: looks along -z, y up, glFrustum + glViewport) becomes
gsplat's OpenCV pair (``camera_to_gsplat``): viewmat = diag(1, -1, -1, 1) camera_from_world
(x right, y down, z forward) and K = [[a_x, 0, b_x], [0, a_y, b_y], [0, 0, 1]] from
``Camera.screen_coefficients`` (x_px = a_x X/U + b_x, y_px = -a_y Y/U + b_y). Both renderers
put pixel (i, j) over [j, j+1) x [i, i+1) and sample it at (j + 0.5, i + 0.5), so K needs no
half-pixel shift: for a symmetric frustum (c_x, c_y) = (W/2, H/2).

Default camera: the first view of a ``cameras.json`` beside the PLY (the 3DGS trainer's
file, OpenCV camera-to-world) when there is one; else ``Camera.framing`` of
``Gaussians.view_bounds()``, the eye on the +z side looking along -z with up = -y (a
capture's frame is COLMAP's, y down): so the fruit label reads "MIXED DROPS" the right way
round, and the donut (a synthetic scene, z up, its icing on +z) is seen from above, icing
and all. From the -z side both show their backs (the label through its own blur, the
donut's bare underside). view_bounds() frames the fruit loosely (the label fills a fifth of
the width): its box is widened by 3 x the scene's largest std dev, 0.245, one halo Gaussian
of 4,721; --eye and --target give a closer view.

The stored references of tests/data (160 x 120, float16; the fruit label seen from 0.75
units in front, the donut from above at 45 degrees, upright) were made with:

    python bench/gsplat_peer.py ../shared/data/gaussian_scenes/fruit_drops_minimal.ply \
        --size 160x120 --eye 0.744 0.119 -1.384 --target 0.744 0.119 -2.134 \
        --float16 --out tests/data/gsplat_fruit_drops.npz
    python bench/gsplat_peer.py ../shared/data/gaussian_donut/fused.ply \
        --size 160x120 --eye 0.002 -0.275 0.324 --target 0.002 0.008 0.041 --up 0 0 1 \
        --float16 --out tests/data/gsplat_donut.npz

An output .npz holds ``image`` (H, W, 3), ``alpha`` (H, W) and ``meta``, a JSON string: the
camera (eye, target, up, fov_y, width, height, near), viewmat and K, eps2d, antialiased,
background, the scene's file name, the gsplat and torch versions and the command line.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shlex
import sys
import time
from pathlib import Path

import numpy as np

# numba and torch share two cores on the build machine: torch's OpenMP threads must sleep,
# not spin, between parallel regions (set before torch is first imported)
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from dofsplat.camera import Camera  # noqa: E402
from dofsplat.gaussians import Gaussians  # noqa: E402

GSPLAT_VERSION = "1.5.3"  # the release whose kernels this script ports
TILE_SIZE = 16  # rasterization(tile_size=16), the default
ALPHA_THRESHOLD = np.float32(1.0 / 255.0)  # Common.h: 1.f / 255.f
MAX_ALPHA = np.float32(0.999)  # a Gaussian never hides what is behind it completely
T_STOP = np.float32(1e-4)  # a pixel whose transmittance would reach this is done
EXTEND = 3.33  # ProjectionEWA3DGSFused.cu: the footprint's half-width in std devs, at most
NEAR_PLANE = 0.01  # rasterization(near_plane=0.01), the default
FAR_PLANE = 1e10  # rasterization(far_plane=1e10)
FIRST_CHUNK = 32  # Gaussians composited at once per tile, doubling up to CHUNK
CHUNK = 1024  # memory: CHUNK x 256 floats per array

# OpenGL camera frame (y up, looks along -z) to OpenCV's (y down, looks along +z)
CV_FROM_GL = np.diag([1.0, -1.0, -1.0, 1.0])


# ----------------------------------------------------------------------------------------
# Camera


def camera_to_gsplat(camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """gsplat's (viewmat, K) for a dofsplat camera.

    viewmat: (4, 4) float64, world to camera in OpenCV's convention (x right, y down,
             z forward: depth U = z)
    K:       (3, 3) float64, intrinsics in pixels; gsplat's pixel (i, j) is sampled at
             (j + 0.5, i + 0.5) as dofsplat's is, so (c_x, c_y) = (W/2, H/2) for a
             symmetric frustum (an off-centre frustum, e.g. ``lens_camera``'s, moves it)
    """
    viewmat = CV_FROM_GL @ camera.camera_from_world()
    a_x, b_x, a_y, b_y = camera.screen_coefficients()
    # x_px = a_x X/U + b_x with X = x_cv, U = z_cv; y_px = -a_y Y/U + b_y with Y = -y_cv
    K = np.array([[a_x, 0.0, b_x], [0.0, a_y, b_y], [0.0, 0.0, 1.0]])
    return viewmat, K


def project_points(viewmat: np.ndarray, K: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(M, 2) pixel positions of world points (M, 3) through gsplat's pinhole (float64):
    mean2d = (f_x x/z + c_x, f_y y/z + c_y), persp_proj in Utils.cuh."""
    p = np.asarray(points, np.float64) @ viewmat[:3, :3].T + viewmat[:3, 3]
    return np.stack([K[0, 0] * p[:, 0] / p[:, 2] + K[0, 2],
                     K[1, 1] * p[:, 1] / p[:, 2] + K[1, 2]], axis=1)


def default_camera(gaussians: Gaussians, width: int, height: int, *, fov_y: float = 40.0,
                   scene_path: str | Path | None = None) -> Camera:
    """The first view of cameras.json beside the scene if there is one, else a camera that
    frames ``view_bounds()`` from the +z side, looking along -z, with up = -y (the trainers'
    COLMAP frame is y down)."""
    if scene_path is not None:
        cameras_json = Path(scene_path).with_name("cameras.json")
        if cameras_json.exists():
            return camera_from_cameras_json(cameras_json, width, height)
    lo, hi = gaussians.view_bounds()
    return Camera.framing(lo, hi, width=width, height=height, fov_y=fov_y,
                          direction=(0.0, 0.0, 1.0), up=(0.0, -1.0, 0.0))


def camera_from_cameras_json(path: str | Path, width: int, height: int, index: int = 0) -> Camera:
    """A dofsplat camera from the 3DGS trainer's cameras.json (entries with ``position``,
    ``rotation`` camera-to-world in OpenCV's frame, ``fy`` and ``height`` in pixels), at the
    requested size with the view's vertical field of view."""
    view = json.loads(Path(path).read_text())[index]
    rotation = np.asarray(view["rotation"], np.float64)  # columns: camera x, y, z in the world
    eye = np.asarray(view["position"], np.float64)
    fov_y = math.degrees(2.0 * math.atan(0.5 * view["height"] / view["fy"]))
    return Camera(eye=tuple(eye), target=tuple(eye + rotation[:, 2]), up=tuple(-rotation[:, 1]),
                  width=width, height=height, fov_y=fov_y, near=NEAR_PLANE)


# ----------------------------------------------------------------------------------------
# Scene file (independent of dofsplat.io, so that the peer stands on its own)


def read_3dgs_ply(path: str | Path) -> Gaussians:
    """A 3DGS trainer's PLY: x y z, f_dc_0..2, f_rest_* (channel-major: red's coefficients
    1..K-1, then green's, then blue's), opacity (logit), scale_0..2 (log), rot_0..3 (w x y z,
    not necessarily unit). Other properties (normals, SuperSplat's ``transform``) are ignored.
    Rows with NaN or inf are dropped (``Gaussians.from_arrays``)."""
    from plyfile import PlyData

    vertex = PlyData.read(str(path))["vertex"]
    names = vertex.data.dtype.names

    def columns(prefix, count=None):
        found = sorted((n for n in names if n.startswith(prefix) and n[len(prefix):].isdigit()),
                       key=lambda n: int(n[len(prefix):]))
        if count is not None and len(found) != count:
            raise ValueError(f"{path}: expected {count} {prefix}* properties, found {len(found)}")
        return np.stack([np.asarray(vertex[n], np.float32) for n in found], axis=1) \
            if found else np.zeros((len(vertex.data), 0), np.float32)

    missing = [n for n in ("x", "y", "z", "opacity") if n not in names]
    if missing:
        raise ValueError(f"{path}: not a 3DGS PLY (no {', '.join(missing)} property)")
    positions = np.stack([np.asarray(vertex[n], np.float32) for n in "xyz"], axis=1)
    f_dc = columns("f_dc_", 3)  # (N, 3)
    f_rest = columns("f_rest_")  # (N, 3 (K - 1))
    if f_rest.shape[1] % 3 or (f_rest.shape[1] // 3 + 1) not in (1, 4, 9, 16):
        raise ValueError(f"{path}: {f_rest.shape[1]} f_rest properties is no SH degree 0-3")
    rest = f_rest.reshape(len(positions), 3, -1).transpose(0, 2, 1)  # (N, K-1, 3)
    sh = np.concatenate([f_dc[:, None, :], rest], axis=1)
    logit = np.asarray(vertex["opacity"], np.float64)
    opacity = (1.0 / (1.0 + np.exp(-logit))).astype(np.float32)
    scales = np.exp(columns("scale_", 3).astype(np.float64)).astype(np.float32)
    rotations = columns("rot_", 4)
    return Gaussians.from_arrays(positions, scales, rotations, opacity, sh, source=str(path))


# ----------------------------------------------------------------------------------------
# The renderer: gsplat.rasterization(..., sh_degree=deg, packed=False) on one camera


def gsplat_render(gaussians: Gaussians, camera: Camera, *, eps2d: float = 0.3,
                  antialiased: bool = False, background=0.0, near_plane: float = NEAR_PLANE,
                  far_plane: float = FAR_PLANE) -> tuple[np.ndarray, np.ndarray]:
    """The image gsplat 1.5.3 draws of ``gaussians`` through ``camera``.

    eps2d:       px^2 added to the 2D covariance's diagonal (gsplat's low-pass filter)
    antialiased: rasterize_mode="antialiased" (Mip-Splatting's opacity compensation)
    background:  scalar or (3,) colour behind the Gaussians
    Returns image (H, W, 3) float32 (not clamped to 1: gsplat's colours are clamped below
    only) and alpha (H, W) float32 = 1 - the final transmittance.
    """
    viewmat, K = camera_to_gsplat(camera)
    width, height = camera.width, camera.height
    footprints = project(gaussians, viewmat, K, width, height, eps2d=eps2d,
                         antialiased=antialiased, near_plane=near_plane, far_plane=far_plane)
    colors = sh_colors(gaussians, viewmat, footprints["visible"])
    tile_ids, gauss_ids = intersect_tiles(footprints["means2d"], footprints["radii"],
                                          footprints["depths"], width, height)
    bg = np.broadcast_to(np.asarray(background, np.float32), (3,))
    return composite(footprints["means2d"], footprints["conics"], footprints["opacities"],
                     colors, tile_ids, gauss_ids, width, height, bg)


def project(gaussians: Gaussians, viewmat: np.ndarray, K: np.ndarray, width: int, height: int,
            *, eps2d: float, antialiased: bool, near_plane: float, far_plane: float) -> dict:
    """Stage 1: gsplat's projection. Returns float32 arrays: means2d (N, 2) px, conics
    (N, 3) (a, b, c) of the inverse 2D covariance, depths (N,), opacities (N,) (times the
    compensation when antialiased), radii (N, 2) int32 px (0: culled), visible (N,) bool."""
    import torch
    from gsplat.cuda._torch_impl import (_fully_fused_projection, _persp_proj,
                                         _quat_scale_to_covar_preci, _world_to_cam)

    means = torch.from_numpy(gaussians.positions)  # [N, 3]
    quats = torch.from_numpy(gaussians.rotations)  # [N, 4]
    scales = torch.from_numpy(gaussians.scales)  # [N, 3]
    viewmats = torch.from_numpy(viewmat.astype(np.float32))[None]  # [1, 4, 4]
    Ks = torch.from_numpy(K.astype(np.float32))[None]  # [1, 3, 3]
    with torch.no_grad():
        covars, _ = _quat_scale_to_covar_preci(quats, scales, compute_preci=False)  # [N, 3, 3]
        _, means2d, depths, conics, compensations = _fully_fused_projection(
            means, covars, viewmats, Ks, width, height, eps2d=eps2d, near_plane=near_plane,
            far_plane=far_plane, calc_compensations=antialiased)
        # the torch twin sizes footprints with 3.33 sigma whatever the opacity; the CUDA
        # kernel that rasterization() calls shrinks them by opacity: recompute its radii
        means_c, covars_c = _world_to_cam(means, covars, viewmats)
        _, covars2d = _persp_proj(means_c, covars_c, Ks, width, height)  # [1, N, 2, 2]
    means2d = means2d[0].numpy()
    depths = depths[0].numpy()
    conics = conics[0].numpy()
    var_x = covars2d[0, :, 0, 0].numpy() + np.float32(eps2d)
    var_y = covars2d[0, :, 1, 1].numpy() + np.float32(eps2d)
    opacities = gaussians.opacity.astype(np.float32)
    if antialiased:
        opacities = opacities * compensations[0].numpy()
    with np.errstate(divide="ignore", invalid="ignore"):
        extend = np.minimum(np.float32(EXTEND),
                            np.sqrt(2.0 * np.log(opacities / ALPHA_THRESHOLD))).astype(np.float32)
        radii = np.stack([np.ceil(extend * np.sqrt(var_x)), np.ceil(extend * np.sqrt(var_y))], 1)
    det = var_x * var_y - covars2d[0, :, 0, 1].numpy() * covars2d[0, :, 1, 0].numpy()
    # the CUDA kernel culls z < near or z > far (the torch twin keeps near < z < far)
    visible = (depths >= near_plane) & (depths <= far_plane) & (det > 0) \
        & (opacities >= ALPHA_THRESHOLD) & np.all(np.isfinite(radii), axis=1) \
        & ((radii[:, 0] > 0) | (radii[:, 1] > 0))  # radius_clip = 0
    visible &= (means2d[:, 0] + radii[:, 0] > 0) & (means2d[:, 0] - radii[:, 0] < width) \
        & (means2d[:, 1] + radii[:, 1] > 0) & (means2d[:, 1] - radii[:, 1] < height)
    radii = np.where(visible[:, None], radii, 0).astype(np.int32)
    return {"means2d": means2d, "conics": conics, "depths": depths, "opacities": opacities,
            "radii": radii, "visible": visible}


def sh_colors(gaussians: Gaussians, viewmat: np.ndarray, visible: np.ndarray) -> np.ndarray:
    """Stage 2: (N, 3) float32 colours, gsplat's ``_spherical_harmonics`` at the direction
    from the camera centre to each mean, + 0.5 and clamped at 0 (rendering.py); 0 where
    not visible (the CUDA kernel's mask)."""
    import torch
    from gsplat.cuda._torch_impl import _spherical_harmonics

    viewmats = torch.from_numpy(viewmat.astype(np.float32))[None]
    with torch.no_grad():
        campos = torch.inverse(viewmats)[:, :3, 3]  # [1, 3]
        dirs = torch.from_numpy(gaussians.positions) - campos  # [N, 3]
        colors = _spherical_harmonics(gaussians.sh_degree, dirs, torch.from_numpy(gaussians.sh))
        colors = torch.clamp_min(colors + 0.5, 0.0)  # "apple-to-apple with Inria's CUDA Backend"
    return np.where(visible[:, None], colors.numpy(), np.float32(0.0))


def intersect_tiles(means2d: np.ndarray, radii: np.ndarray, depths: np.ndarray, width: int,
                    height: int) -> tuple[np.ndarray, np.ndarray]:
    """Stage 3 (IntersectTile.cu): the (tile, Gaussian) pairs sorted by tile, then depth,
    then Gaussian index. Returns tile_ids (M,) int64 (row-major over the tile grid) and
    gauss_ids (M,) int64."""
    tile_width = math.ceil(width / TILE_SIZE)
    tile_height = math.ceil(height / TILE_SIZE)
    ts = np.float32(TILE_SIZE)
    tile_xy = means2d / ts  # float32, as the kernel
    tile_r = radii.astype(np.float32) / ts
    # (uint32_t)floor(x) of a negative x saturates to 0 on the GPU, then min(..., grid)
    lo = np.floor(tile_xy - tile_r)
    hi = np.ceil(tile_xy + tile_r)
    grid = np.array([tile_width, tile_height], np.float32)
    lo = np.clip(lo, 0, grid).astype(np.int64)
    hi = np.clip(hi, 0, grid).astype(np.int64)
    hit = np.all(radii > 0, axis=1)
    nx = np.where(hit, hi[:, 0] - lo[:, 0], 0)
    ny = np.where(hit, hi[:, 1] - lo[:, 1], 0)
    counts = nx * ny
    gauss_ids = np.repeat(np.arange(len(radii), dtype=np.int64), counts)
    k = np.arange(counts.sum(), dtype=np.int64) - np.repeat(np.cumsum(counts) - counts, counts)
    row = np.repeat(nx, counts)
    tile_ids = (lo[gauss_ids, 1] + k // np.maximum(row, 1)) * tile_width \
        + lo[gauss_ids, 0] + k % np.maximum(row, 1)
    # the key is tile << 32 | float bits of the depth (positive depths sort as floats do)
    depth_bits = depths.astype(np.float32).view(np.uint32)[gauss_ids]
    order = np.lexsort((depth_bits, tile_ids))  # stable: equal keys keep Gaussian order
    return tile_ids[order], gauss_ids[order]


def composite(means2d, conics, opacities, colors, tile_ids, gauss_ids, width, height,
              background) -> tuple[np.ndarray, np.ndarray]:
    """Stage 4 (RasterizeToPixels3DGSFwd.cu): every tile's 256 pixels, front to back over
    its sorted Gaussians, in float32. The sequential T_k = T_{k-1} (1 - alpha_k) of the
    kernel is a cumulative product (skipped Gaussians multiply by 1); since it never grows,
    "stop before the first Gaussian whose next_T <= 1e-4" keeps exactly the Gaussians whose
    next_T > 1e-4."""
    tile_width = math.ceil(width / TILE_SIZE)
    tile_height = math.ceil(height / TILE_SIZE)
    image = np.zeros((tile_height * TILE_SIZE, tile_width * TILE_SIZE, 3), np.float32)
    transmittance = np.ones((tile_height * TILE_SIZE, tile_width * TILE_SIZE), np.float32)
    jj, ii = np.meshgrid(np.arange(TILE_SIZE), np.arange(TILE_SIZE))
    starts = np.searchsorted(tile_ids, np.arange(tile_width * tile_height + 1))
    one = np.float32(1.0)
    for tile in range(tile_width * tile_height):
        begin, end = starts[tile], starts[tile + 1]
        if begin == end:
            continue
        ty, tx = divmod(tile, tile_width)
        px = (tx * TILE_SIZE + jj).ravel().astype(np.float32) + np.float32(0.5)  # (256,)
        py = (ty * TILE_SIZE + ii).ravel().astype(np.float32) + np.float32(0.5)
        T = np.ones(TILE_SIZE * TILE_SIZE, np.float32)
        C = np.zeros((TILE_SIZE * TILE_SIZE, 3), np.float32)
        active = np.arange(TILE_SIZE * TILE_SIZE)  # the pixels not done yet
        chunk, first = FIRST_CHUNK, begin
        while first < end and active.size:
            g = gauss_ids[first:min(first + chunk, end)]
            first, chunk = first + chunk, min(2 * chunk, CHUNK)  # opaque tiles stop early
            dx = means2d[g, 0, None] - px[active]  # (n, pixels): the kernel's mean - pixel
            dy = means2d[g, 1, None] - py[active]
            a, b, c = conics[g, 0, None], conics[g, 1, None], conics[g, 2, None]
            sigma = np.float32(0.5) * (a * dx * dx + c * dy * dy) + b * dx * dy
            alpha = np.minimum(MAX_ALPHA, opacities[g, None] * np.exp(-sigma))
            used = (sigma >= 0) & (alpha >= ALPHA_THRESHOLD)
            # T before this chunk, then the running products: next_T after every Gaussian
            factor = np.where(used, one - alpha, one)
            running = np.cumprod(np.concatenate([T[None, active], factor]), axis=0)
            before_T, next_T = running[:-1], running[1:]
            kept = next_T > T_STOP  # a prefix of the chunk: next_T never grows
            C[active] += np.where(used & kept, alpha * before_T, np.float32(0.0)).T @ colors[g]
            n_kept = kept.sum(axis=0)
            T[active] = np.where(n_kept > 0, next_T[np.maximum(n_kept - 1, 0),
                                                    np.arange(active.size)], T[active])
            active = active[kept[-1]]
        ys = slice(ty * TILE_SIZE, (ty + 1) * TILE_SIZE)
        xs = slice(tx * TILE_SIZE, (tx + 1) * TILE_SIZE)
        image[ys, xs] = C.reshape(TILE_SIZE, TILE_SIZE, 3)
        transmittance[ys, xs] = T.reshape(TILE_SIZE, TILE_SIZE)
    image = image[:height, :width] + transmittance[:height, :width, None] * background
    return image.astype(np.float32), (one - transmittance[:height, :width]).astype(np.float32)


# ----------------------------------------------------------------------------------------
# Command line


def _size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"size must be WIDTHxHEIGHT, got {text!r}") from None
    return w, h


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("scene", type=Path, help="a 3DGS PLY")
    parser.add_argument("--size", type=_size, default=(640, 480), help="WIDTHxHEIGHT")
    parser.add_argument("--eye", type=float, nargs=3)
    parser.add_argument("--target", type=float, nargs=3)
    parser.add_argument("--up", type=float, nargs=3, default=(0.0, -1.0, 0.0))
    parser.add_argument("--fov", type=float, default=40.0, help="vertical, degrees")
    parser.add_argument("--eps2d", type=float, default=0.3)
    parser.add_argument("--antialiased", action="store_true")
    parser.add_argument("--background", type=float, nargs=3, default=(0.0, 0.0, 0.0))
    parser.add_argument("--out", type=Path, required=True, help="image.npz")
    parser.add_argument("--float16", action="store_true", help="store image and alpha as float16")
    parser.add_argument("--png", type=Path, help="also an 8-bit preview (alpha over black)")
    args = parser.parse_args(argv)

    import gsplat
    import torch

    if gsplat.__version__ != GSPLAT_VERSION:
        print(f"warning: gsplat {gsplat.__version__} installed; this port follows "
              f"{GSPLAT_VERSION}", file=sys.stderr)
    width, height = args.size
    gaussians = read_3dgs_ply(args.scene)
    if (args.eye is None) != (args.target is None):
        parser.error("give both --eye and --target, or neither")
    if args.eye is not None:
        camera = Camera(eye=tuple(args.eye), target=tuple(args.target), up=tuple(args.up),
                        width=width, height=height, fov_y=args.fov, near=NEAR_PLANE)
    else:
        camera = default_camera(gaussians, width, height, fov_y=args.fov, scene_path=args.scene)
    t0 = time.perf_counter()
    image, alpha = gsplat_render(gaussians, camera, eps2d=args.eps2d,
                                 antialiased=args.antialiased, background=args.background)
    seconds = time.perf_counter() - t0
    viewmat, K = camera_to_gsplat(camera)
    meta = {
        "scene": args.scene.name, "gaussians": len(gaussians), "sh_degree": gaussians.sh_degree,
        "camera": {"eye": camera.eye, "target": camera.target, "up": camera.up,
                   "fov_y": camera.fov_y, "width": width, "height": height,
                   "near": camera.near},
        "viewmat": viewmat.tolist(), "K": K.tolist(), "eps2d": args.eps2d,
        "antialiased": args.antialiased, "background": list(args.background),
        "near_plane": NEAR_PLANE, "far_plane": FAR_PLANE, "tile_size": TILE_SIZE,
        "gsplat": gsplat.__version__, "torch": torch.__version__, "seconds": round(seconds, 2),
        "command": "python bench/gsplat_peer.py " + " ".join(shlex.quote(a) for a in
                                                             (argv or sys.argv[1:])),
    }
    dtype = np.float16 if args.float16 else np.float32
    args.out.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(args.out, image=image.astype(dtype), alpha=alpha.astype(dtype),
                        meta=np.array(json.dumps(meta)))
    if args.png is not None:
        from PIL import Image

        Image.fromarray((np.clip(image, 0, 1) * 255 + 0.5).astype(np.uint8)).save(args.png)
    print(f"{args.scene.name}: {len(gaussians):,} Gaussians, {width}x{height} in {seconds:.1f} s "
          f"-> {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
