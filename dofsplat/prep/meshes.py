"""Triangle meshes to surfels: area-uniform sampling (issue 4, item 2).

A mesh becomes surfels in one of two ways:

* **sampling** (the default): ``count`` points spread over the surface in proportion to
  area, as blue noise. First 2 x count stratified candidates: the faces by systematic
  sampling of the cumulative area (each face gets the floor or the ceiling of its share)
  and the point inside a face from the R2 low-discrepancy sequence (Roberts 2018), mapped
  to the triangle by the square-root map that keeps areas uniform. Then weighted sample
  elimination (Yuksel 2015) thins them to ``count`` points with no two too close. The
  result is deterministic.
* **one surfel per vertex** (``count="vertices"``): a vertex stands for one third of the
  area of the faces around it (its barycentric cell); vertices that share a position (UV
  seams) become one surfel.

Normals come from the surface: the vertex normals (area-weighted face normals)
interpolated across the face. At a hard edge or corner (a vertex with a face around it
more than CREASE_DEG from its normal) the face's own normal stands in for the vertex
normal, and the flat face normal is used wherever the interpolated one still differs
from it by more than CREASE_DEG. With those normals a sample on a flat face carries a disk tilted
against the face, and on a coarse mesh (Spot: 2,930 vertices) neighbouring disks stand at
different depths and leave streaks along the edges; so by default (``smooth=True``) the
samples move onto the Phong tessellation of their faces (Boubekeur & Alexa 2008,
:func:`phong_positions`), the smooth surface that those normals describe: Spot in close-up
goes from 0.91 / 0.94 to 0.96 / 0.97 of its pixels in 1 +- 0.1. Colours come from the texture (bilinear, REPEAT wrapping, at the
mip level that matches the sample spacing), else the vertex colours, times the base colour
factor. Opacity follows the glTF alpha modes: OPAQUE ignores alpha, MASK drops samples whose
alpha is below the cutoff, BLEND keeps alpha as the surfel opacity (and drops samples
under 1/255).

Radii come from the local sample density. A sample stands for an area a: sampled points
share the area equally (a = A / count), a vertex stands for its cell. In the surfel
convention of :mod:`dofsplat.surfels` (a grid of spacing h wants r = h) that is r_a =
sqrt(a); a sampled point gets r_a = h x (its mean distance to its RADIUS_NEIGHBOURS nearest
neighbours) / (the rms of that distance), h = sqrt(A / count), so that a point in a sparse
spot covers more. Blue noise is not a grid: Gaussians of standard deviation h / 2 over it
sum to 1 +- 0.1 on only 2/3 of a surface seen close up, and no weight per surfel can flatten
the dips between samples. So the disks are RADIUS_SCALE x wider, r = 1.3 r_a, and
``Surfels.weight`` = 1 / 1.3^2 keeps the area each stands for (a splat deposits
r^2 x weight). Then the per-surfel normalisation of :mod:`dofsplat.prep.normalise` (paper
Section 6.3; by default the object-space method) evens out the rest: on a square seen at 6
pixels per sample spacing, 98 % of the pixels then sum to 1 +- 0.1, against 79 % with
r = r_a (bench/RESULTS.md, "Sampled meshes in close-up").
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from ..jit import numba
import numpy as np

from ..errors import DofsplatError
from ..parallel import interrupt_after
from ..colors import srgb_to_linear
from ..surfels import Material, Surfels
from .neighbours import QUERY_CHUNK

DEFAULT_MIN_SAMPLES = 200_000  # default count: the vertex count, but at least this many
DEFAULT_COLOR = (0.8, 0.8, 0.8, 1.0)  # linear RGBA of a mesh without colour or texture
CREASE_DEG = 40.0  # vertex normals further than this from the face normal: a hard edge
PHONG_SHAPE = 0.75  # Phong tessellation's shape factor (Boubekeur & Alexa recommend 3/4)
ALPHA_MODES = ("OPAQUE", "MASK", "BLEND")
MIN_OPACITY = 1.0 / 255.0  # BLEND samples below this cannot change an 8-bit pixel: dropped
MAX_SAMPLES = 50_000_000  # a larger count is a mistake, not a mesh (2.4 GB of surfels)
OVERSAMPLE = 2  # candidates per sample (Yuksel: 3-5; 3 gains ~3 % uniformity at 2x the time,
#                1.5 leaves weights as low as 0.2 where 2 keeps them above 0.36)
MAX_ELIMINATION = 3_000_000  # above this many samples, stratified samples only (memory)
RADIUS_NEIGHBOURS = 6  # neighbours whose mean distance sets a sample's radius
RADIUS_SCALE = 1.3  # disk radius over the radius of the area a surfel stands for (module
#                     docstring). A square at 6 px per spacing, normalised, reads 0.79 /
#                     0.95 / 0.98 / 0.99 of pixels in 1 +- 0.1 with 1.0 / 1.2 / 1.3 / 1.4
#                     (bench/uniformity.py --radius-scale; bench/RESULTS.md)
_WORKERS = 2  # k-d tree query threads: this is a 2-core machine shared with other work

# R2 sequence (Roberts 2018): the plastic number's powers give the best 2D additive recurrence
_PLASTIC = 1.32471795724474602596
_R2_STEP = (1.0 / _PLASTIC, 1.0 / _PLASTIC**2)


@dataclass
class MeshPart:
    """One piece of a mesh with one material.

    vertices:      (V, 3) float, world units
    faces:         (F, 3) int vertex indices, counter-clockwise seen from the front
    vertex_colors: (V, 3 or 4) float32 linear RGB(A) in [0, 1], or None
    uv:            (V, 2) float texture coordinates, origin at the bottom left, or None
    texture:       (H, W, 4) float32 linear RGBA in [0, 1], row 0 at the top, or None
    base_color:    (4,) linear RGBA factor on the texture or vertex colours (glTF
                   baseColorFactor), the colour itself when there is neither; None: white
                   on a texture or vertex colours, else DEFAULT_COLOR
    alpha_mode:    "OPAQUE", "MASK" or "BLEND" (glTF alphaMode)
    alpha_cutoff:  MASK: samples with alpha below this are dropped
    double_sided:  also emit back-facing twins, so that the part shows from both sides
    """

    vertices: np.ndarray
    faces: np.ndarray
    vertex_colors: np.ndarray | None = None
    uv: np.ndarray | None = None
    texture: np.ndarray | None = None
    base_color: tuple | None = None
    alpha_mode: str = "OPAQUE"
    alpha_cutoff: float = 0.5
    double_sided: bool = False
    name: str = ""

    def __post_init__(self):
        self.vertices = np.asarray(self.vertices, dtype=np.float64)
        if self.vertices.ndim != 2 or self.vertices.shape[1] != 3:
            raise DofsplatError(f"mesh vertices must have shape (V, 3), got {self.vertices.shape}")
        faces = np.asarray(self.faces)
        if faces.size == 0:
            faces = faces.reshape(0, 3)
        if faces.ndim != 2 or faces.shape[1] != 3 or not np.issubdtype(faces.dtype, np.integer):
            raise DofsplatError(f"mesh faces must be (F, 3) vertex indices, got {faces.shape} "
                                f"{faces.dtype}")
        v = len(self.vertices)
        if faces.size and (faces.min() < 0 or faces.max() >= v):
            raise DofsplatError(f"mesh faces refer to vertex {int(faces.max())} (or below 0), "
                                f"but there are {v} vertices")
        self.faces = faces.astype(np.int64)
        for name, width in (("vertex_colors", (3, 4)), ("uv", (2,))):
            a = getattr(self, name)
            if a is not None:
                a = np.asarray(a, dtype=np.float32 if name == "vertex_colors" else np.float64)
                if a.ndim != 2 or a.shape[0] != v or a.shape[1] not in width:
                    raise DofsplatError(f"mesh {name} must have one row per vertex, got "
                                        f"{a.shape} for {v} vertices")
                setattr(self, name, a)
        if self.texture is not None:
            t = np.asarray(self.texture, dtype=np.float32)
            if t.ndim != 3 or t.shape[2] != 4 or t.shape[0] < 1 or t.shape[1] < 1:
                raise DofsplatError(f"a texture must be (H, W, 4) RGBA, got {t.shape}")
            self.texture = t
        if self.base_color is not None:
            self.base_color = tuple(float(c) for c in self.base_color)
            if len(self.base_color) != 4:
                raise DofsplatError(f"base_color must be RGBA, got {self.base_color}")
        self.alpha_mode = str(self.alpha_mode).upper()
        if self.alpha_mode not in ALPHA_MODES:
            raise DofsplatError(f"alpha mode must be one of {', '.join(ALPHA_MODES)}, got "
                                f"{self.alpha_mode!r}")


def mesh_to_surfels(parts: MeshPart | list[MeshPart], count: int | str | None = None, *,
                    material: Material | None = None, smooth: bool = True,
                    normalise: str = "object", progress: bool = True,
                    source: str = "mesh") -> Surfels:
    """Surfels on the surface of a triangle mesh.

    parts: one MeshPart or several (a glTF scene: one per primitive and material), sampled
    together so that the density is the same on all of them.
    count: the number of samples over the whole mesh (before MASK drops samples and
    double-sided parts double them); None for the default, max(vertex count,
    DEFAULT_MIN_SAMPLES); "vertices" for one surfel per vertex.
    smooth: samples lie on the Phong tessellation of the faces, which agrees with the
    interpolated normals (:func:`phong_positions`); False keeps them on the flat faces.
    Vertices lie on both, so it does not change ``count="vertices"``.
    normalise: the per-surfel normalisation (:func:`dofsplat.prep.normalise.normalise`):
    "object" (default), "render" or "none" (weights 1 / RADIUS_SCALE^2 as sampled).
    progress: progress bars on stderr for long steps (only when it is a terminal).
    Raises DofsplatError for a mesh without faces of non-zero area.
    """
    from .normalise import check_method
    from .normalise import normalise as normalise_surfels

    check_method(normalise)
    parts = [parts] if isinstance(parts, MeshPart) else list(parts)
    geometry = [_face_geometry(p) for p in parts]
    total_area = sum(float(g.area.sum()) for g in geometry)
    n_faces = sum(len(p.faces) for p in parts)
    if n_faces == 0:
        raise DofsplatError(f"{source}: the mesh has no faces (a mesh file needs triangles; "
                            "save bare points as PLY to render them as a point cloud)")
    if not (total_area > 0 and math.isfinite(total_area)):
        raise DofsplatError(f"{source}: all {n_faces} faces of the mesh have zero area "
                            "(or non-finite vertices)")

    if count == "vertices":
        pieces = _vertex_surfels(parts, geometry)
    else:
        n = _sample_count(count, parts)
        pieces = _sampled_surfels(parts, geometry, n, total_area, smooth)
    pieces = [p for p in pieces if len(p["positions"])]
    if not pieces:
        raise DofsplatError(f"{source}: no surfels left: every sample fell where the alpha "
                            "mask is below its cutoff")
    arrays = {k: np.concatenate([p[k] for p in pieces]) for k in pieces[0]}
    arrays["radius"] = arrays["radius"] * RADIUS_SCALE
    arrays["weight"] = np.full(len(arrays["radius"]), 1.0 / RADIUS_SCALE**2)
    surfels = Surfels.from_arrays(**arrays, material=material, source=source)
    return normalise_surfels(surfels, normalise, progress=progress)


# -- per-face geometry -------------------------------------------------------------------


@dataclass
class _Faces:
    """Per-face quantities of one part (faces of zero or non-finite area removed)."""

    index: np.ndarray  # (F',) indices into part.faces of the faces kept
    area: np.ndarray  # (F',) float64
    normal: np.ndarray  # (F', 3) float64 unit
    vertex_normal: np.ndarray  # (V, 3) float64 unit (or zero for unused vertices)
    crease: np.ndarray  # (V,) bool: a face around the vertex is > CREASE_DEG from its normal
    undefined: np.ndarray  # (V,) bool: no face, or faces that cancel (vertex_normal: one face's)


def _face_geometry(part: MeshPart) -> _Faces:
    v = part.vertices
    if len(part.faces) == 0:
        z = np.zeros(0)
        return _Faces(np.zeros(0, np.int64), z, np.zeros((0, 3)), np.zeros_like(v),
                      np.zeros(len(v), bool), np.ones(len(v), bool))
    p0, p1, p2 = (v[part.faces[:, i]] for i in range(3))
    with np.errstate(invalid="ignore", over="ignore"):
        cross = np.cross(p1 - p0, p2 - p0)
        double_area = np.linalg.norm(cross, axis=1)
    keep = np.isfinite(double_area) & (double_area > 0)
    index = np.flatnonzero(keep)
    cross, double_area = cross[keep], double_area[keep]
    normal = cross / double_area[:, None]
    # area-weighted vertex normals: the face cross products summed at their corners
    acc = np.zeros_like(v)
    for i in range(3):
        np.add.at(acc, part.faces[index, i], cross)
    length = np.linalg.norm(acc, axis=1)
    vertex_normal = np.divide(acc, length[:, None], out=np.zeros_like(acc),
                              where=length[:, None] > 0)
    # where the faces around a vertex cancel (a fold, back-to-back faces), one of them
    largest = float(double_area.max()) if double_area.size else 0.0
    cancelled = np.flatnonzero(length <= 1e-12 * largest)
    if cancelled.size and index.size:
        some_face = np.zeros(len(v), np.int64)
        for i in range(3):
            some_face[part.faces[index, i]] = np.arange(len(index))
        vertex_normal[cancelled] = normal[some_face[cancelled]]
    # a hard edge or corner: some face around the vertex turns away from its normal
    min_cos = np.ones(len(v))
    for i in range(3):
        corner = part.faces[index, i]
        np.minimum.at(min_cos, corner, np.sum(vertex_normal[corner] * normal, axis=1))
    crease = min_cos < math.cos(math.radians(CREASE_DEG))
    undefined = np.zeros(len(v), bool)
    undefined[cancelled] = True
    return _Faces(index, 0.5 * double_area, normal, vertex_normal, crease, undefined)


def vertex_normals(vertices, faces) -> np.ndarray:
    """(V, 3) unit area-weighted vertex normals of a triangle mesh, the normals this module
    interpolates; zero where they are undefined: a vertex that no face of non-zero area
    uses, or whose faces cancel (back-to-back faces)."""
    geo = _face_geometry(MeshPart(vertices, faces))
    return np.where(geo.undefined[:, None], 0.0, geo.vertex_normal)


def _sample_count(count, parts) -> int:
    if count is None:
        return max(sum(len(p.vertices) for p in parts), DEFAULT_MIN_SAMPLES)
    whole = isinstance(count, (int, np.integer)) and not isinstance(count, bool)
    if not whole:
        raise DofsplatError(f"the sample count must be a whole number or 'vertices', got "
                            f"{count!r}")
    if not 1 <= count <= MAX_SAMPLES:
        raise DofsplatError(f"the sample count must be between 1 and {MAX_SAMPLES:,}, got "
                            f"{count:,}")
    return int(count)


# -- sampling ----------------------------------------------------------------------------


def _sampled_surfels(parts, geometry, n: int, total_area: float, smooth: bool) -> list[dict]:
    """``n`` area-uniform samples over all parts: stratified candidates, thinned to blue
    noise by weighted sample elimination, radii from the local density."""
    m = int(round(n * OVERSAMPLE)) if n <= MAX_ELIMINATION else n
    part_id, face, bary, positions = _candidates(parts, geometry, m, total_area)
    if m > n:
        keep = poisson_eliminate(positions, total_area, n)
        part_id, face, bary, positions = part_id[keep], face[keep], bary[keep], positions[keep]
    radius = density_radius(positions, math.sqrt(total_area / n))
    pieces = []
    for p, (part, geo) in enumerate(zip(parts, geometry)):
        take = part_id == p
        if take.any():
            pieces.extend(_surfels_at(part, geo, face[take], bary[take], positions[take],
                                      radius[take], smooth))
    return pieces


def _candidates(parts, geometry, m: int, total_area: float):
    """m stratified area-uniform points: (part index, kept-face index, barycentric, position).

    Sample i sits at cumulative area (i + 1/2) A / m, so every face gets the floor or the
    ceiling of its share (no clumps of faces), and at the i-th point of the R2 sequence
    inside its face (consecutive points of R2 are well spread).
    """
    areas = [g.area for g in geometry]
    cum = np.cumsum(np.concatenate(areas))
    first_face = np.cumsum([0] + [len(a) for a in areas])
    i = np.arange(m, dtype=np.int64)
    u = (i + 0.5) * (total_area / m)
    g_face = np.minimum(np.searchsorted(cum, u, side="right"), len(cum) - 1)
    part_id = np.searchsorted(first_face, g_face, side="right") - 1
    face = g_face - first_face[part_id]
    bary = _r2_barycentric(i)
    positions = np.empty((m, 3))
    for p, (part, geo) in enumerate(zip(parts, geometry)):
        take = np.flatnonzero(part_id == p)
        corners = part.faces[geo.index[face[take]]]
        positions[take] = np.einsum("nk,nkd->nd", bary[take], part.vertices[corners])
    return part_id, face, bary, positions


def _r2_barycentric(index: np.ndarray) -> np.ndarray:
    """(n, 3) barycentric coordinates, uniform over the triangle, from the R2 sequence."""
    r1 = np.mod(0.5 + _R2_STEP[0] * index, 1.0)
    r2 = np.mod(0.5 + _R2_STEP[1] * index, 1.0)
    # the square-root map (Osada et al. 2002) is continuous, so well-spread points in the
    # square stay well spread in the triangle
    s = np.sqrt(r1)
    return np.stack([1.0 - s, s * (1.0 - r2), s * r2], axis=1)


def density_radius(positions: np.ndarray, spacing: float, k: int = RADIUS_NEIGHBOURS) -> np.ndarray:
    """(n,) radii proportional to each point's mean distance to its k nearest neighbours,
    scaled so that their mean square is spacing**2 (the total area stays A = n h^2).

    A point in a sparse spot gets a larger disk and one in a crowd a smaller one, which
    evens out the accumulated splat weight: on a blue-noise sampled plane 60 to 78 % of
    the pixels lie within 1 +- 0.1, against 30 to 37 % with one radius for all
    (docs/formats.md gives the setting).
    """
    from scipy.spatial import cKDTree

    n = len(positions)
    if n <= k:
        return np.full(n, spacing)
    tree = cKDTree(positions)
    dist = np.empty((n, k + 1))
    for start in range(0, n, QUERY_CHUNK):  # Ctrl-C is held a chunk at a time, no longer
        stop = min(n, start + QUERY_CHUNK)
        with interrupt_after():  # (its threads write into the result: parallel.py)
            dist[start:stop] = tree.query(positions[start:stop], k=k + 1, workers=_WORKERS)[0]
    mean = dist[:, 1:].mean(axis=1)
    rms = math.sqrt(float(np.mean(mean**2)))
    if not rms > 0:
        return np.full(n, spacing)
    # coincident points (a degenerate mesh) would get radius 0: keep them at the spacing
    return np.where(mean > 0, spacing * mean / rms, spacing)


def poisson_eliminate(points: np.ndarray, area: float, n_keep: int) -> np.ndarray:
    """Boolean mask of n_keep of the points, thinned to blue noise (Yuksel 2015).

    Weighted sample elimination: each point's weight is sum_j (1 - d_ij / 2 r_max)^8 over
    its neighbours within 2 r_max, where r_max = sqrt(A / (2 sqrt(3) n_keep)) is the Poisson
    disk radius of a hexagonal packing of n_keep points on area A; the point with the
    largest weight goes and its neighbours' weights drop, until n_keep remain. Neighbours
    are found in a uniform grid of cells 2 r_max wide (the 27 cells around a point's own).
    """
    points = np.ascontiguousarray(points, dtype=np.float64)
    m = len(points)
    if n_keep >= m:
        return np.ones(m, bool)
    r_max = math.sqrt(area / (2.0 * math.sqrt(3.0) * n_keep))
    # Yuksel's weight limiting: distances below r_min count as r_min
    r_min = r_max * (1.0 - (n_keep / m) ** 1.5) * 0.65
    order, cell_of, cell_start, neighbours = _cell_grid(points, 2.0 * r_max)
    alive_sorted = _eliminate(points[order], cell_of, cell_start, neighbours, r_max, r_min,
                              n_keep)
    alive = np.empty(m, bool)
    alive[order] = alive_sorted
    return alive


def _cell_grid(points: np.ndarray, cell: float):
    """A uniform grid over the points, as flat arrays.

    Returns order (the points sorted by cell), cell_of (the cell of each sorted point),
    cell_start (C + 1,) (cell c holds sorted points cell_start[c]:cell_start[c+1]) and
    neighbours (C, 27) (the occupied cells around each cell, itself included; -1 if empty).
    """
    lo = points.min(axis=0)
    ijk = np.floor((points - lo) / cell).astype(np.int64)
    dims = ijk.max(axis=0) + 3  # a margin of one cell on each side for the neighbour offsets
    if float(np.prod(dims.astype(np.float64))) > 2.0**62:
        raise DofsplatError("the mesh is too large for its sample spacing (grid overflow)")
    ijk += 1
    key = (ijk[:, 0] * dims[1] + ijk[:, 1]) * dims[2] + ijk[:, 2]
    order = np.argsort(key, kind="stable")
    key = key[order]
    new_cell = np.empty(len(key), bool)
    new_cell[0] = True
    np.not_equal(key[1:], key[:-1], out=new_cell[1:])
    cell_start = np.flatnonzero(new_cell)
    cells = key[cell_start]
    cell_of = np.cumsum(new_cell) - 1
    offsets = np.array([(dx * dims[1] + dy) * dims[2] + dz for dx in (-1, 0, 1)
                        for dy in (-1, 0, 1) for dz in (-1, 0, 1)], np.int64)
    # one offset at a time: sorted queries, which searchsorted walks fast
    wanted = offsets[:, None] + cells[None, :]
    found = np.minimum(np.searchsorted(cells, wanted), len(cells) - 1)
    neighbours = np.where(cells[found] == wanted, found, -1).T.copy()
    return order, cell_of, np.append(cell_start, len(key)).astype(np.int64), neighbours


@numba.njit(cache=True)
def _eliminate(points, cell_of, cell_start, neighbours, r_max, r_min, n_keep):
    """The elimination loop; returns the mask of survivors.

    points: (m, 3) float64 sorted by cell; the grid as _cell_grid returns it. The max-heap
    holds each point once with the weight it had when last sifted: weights only fall, so a
    top whose weight has fallen since is sifted down again with its current weight (a lazy
    decrease-key) and only a top that is up to date is eliminated.
    """
    m = points.shape[0]
    weight = np.zeros(m)
    alive = np.ones(m, np.bool_)
    for i in range(m):
        weight[i] = _neighbour_weight(points, i, cell_of, cell_start, neighbours, alive,
                                      r_max, r_min, 0.0)
    heap = np.arange(m)
    key = weight.copy()
    for i in range(m // 2 - 1, -1, -1):
        _sift_down(heap, key, i, m)
    n = m
    while n > n_keep:
        top = heap[0]
        if key[top] > weight[top]:  # stale: re-sift with the current weight
            key[top] = weight[top]
            _sift_down(heap, key, 0, n)
            continue
        alive[top] = False
        n -= 1
        heap[0] = heap[n]
        _sift_down(heap, key, 0, n)
        _neighbour_weight(points, top, cell_of, cell_start, neighbours, alive, r_max, r_min,
                          -1.0, weight)
    return alive


@numba.njit(cache=True, inline="always")
def _neighbour_weight(points, i, cell_of, cell_start, neighbours, alive, r_max, r_min,
                      sign, weight=None):
    """sum_j (1 - max(d_ij, r_min) / 2 r_max)^8 over the live neighbours j of i within
    2 r_max; with ``weight`` given, adds sign x each term to weight[j] instead."""
    two_r = 2.0 * r_max
    inv = 1.0 / two_r
    x, y, z = points[i, 0], points[i, 1], points[i, 2]
    total = 0.0
    for c in neighbours[cell_of[i]]:
        if c < 0:
            continue
        for j in range(cell_start[c], cell_start[c + 1]):
            if j == i or not alive[j]:
                continue
            d2 = (x - points[j, 0]) ** 2 + (y - points[j, 1]) ** 2 + (z - points[j, 2]) ** 2
            if d2 < two_r * two_r:
                t = 1.0 - max(math.sqrt(d2), r_min) * inv
                t *= t
                t *= t
                if weight is None:
                    total += t * t
                else:
                    weight[j] += sign * t * t
    return total


@numba.njit(cache=True)
def _sift_down(heap, key, i, n):
    """Restore the max-heap below position i (heap holds point indices, key their keys)."""
    item = heap[i]
    while True:
        child = 2 * i + 1
        if child >= n:
            break
        if child + 1 < n and key[heap[child + 1]] > key[heap[child]]:
            child += 1
        if key[heap[child]] <= key[item]:
            break
        heap[i] = heap[child]
        i = child
    heap[i] = item


def phong_positions(vertices: np.ndarray, vertex_normals: np.ndarray, bary: np.ndarray,
                    shape: float = PHONG_SHAPE) -> np.ndarray:
    """Points on the Phong tessellation of their triangles (Boubekeur & Alexa 2008).

    vertices, vertex_normals: (n, 3, 3) the corners of each point's triangle and their
    unit normals (the face's own normal at a hard corner); bary: (n, 3). The flat point
    p = sum b_i v_i is projected onto each corner's tangent plane, pi_i(p) = p - ((p - v_i)
    . n_i) n_i, and p* = (1 - shape) p + shape sum b_i pi_i(p). The surface passes through
    the vertices and bulges between them as the normals say, so that disks oriented by the
    interpolated normals lie on it; a corner with the face's normal does not move p.
    """
    p = np.einsum("nk,nkd->nd", bary, vertices)
    height = np.einsum("nkd,nkd->nk", p[:, None, :] - vertices, vertex_normals)  # (n, 3)
    return p - shape * np.einsum("nk,nk,nkd->nd", bary, height, vertex_normals)


def _surfels_at(part: MeshPart, geo: _Faces, local: np.ndarray, bary: np.ndarray,
                positions: np.ndarray, radius: np.ndarray, smooth: bool) -> list[dict]:
    """Surfels at barycentric points of the kept faces ``local`` of one part; smooth: on
    the Phong tessellation of the faces (:func:`phong_positions`), else on the flat faces."""
    corners = part.faces[geo.index[local]]  # (n, 3) vertex indices
    face_normal = geo.normal[local]
    # corner normals: the vertex normal, or the face's own at a hard edge or corner
    corner_normal = np.where(geo.crease[corners][:, :, None], face_normal[:, None, :],
                             geo.vertex_normal[corners])
    if smooth:
        positions = phong_positions(part.vertices[corners], corner_normal, bary)
    interpolated = np.einsum("nk,nkd->nd", bary, corner_normal)
    length = np.linalg.norm(interpolated, axis=1)
    interpolated = np.divide(interpolated, length[:, None], out=np.zeros_like(interpolated),
                             where=length[:, None] > 0)
    crease = np.sum(interpolated * face_normal, axis=1) < math.cos(math.radians(CREASE_DEG))
    normals = np.where(crease[:, None], face_normal, interpolated)

    uv = None
    if part.uv is not None:
        uv = np.einsum("nk,nkd->nd", bary, part.uv[corners])
    vcol = None
    if part.vertex_colors is not None:
        vcol = np.einsum("nk,nkd->nd", bary, part.vertex_colors[corners].astype(np.float64))
    rgba = _colors(part, len(positions), uv, vcol, geo)
    return _finish(part, positions, normals, radius, rgba)


def _vertex_surfels(parts, geometry) -> list[dict]:
    """One surfel per vertex: its barycentric cell's area and normal, merged over seams."""
    pieces = []
    for part, geo in zip(parts, geometry):
        if geo.area.size == 0:
            continue
        area = np.zeros(len(part.vertices))
        for i in range(3):
            np.add.at(area, part.faces[geo.index, i], geo.area / 3.0)
        used = np.flatnonzero(area > 0)
        uv = part.uv[used] if part.uv is not None else None
        vcol = part.vertex_colors[used] if part.vertex_colors is not None else None
        rgba = _colors(part, used.size, uv, vcol, geo)
        piece = _finish(part, part.vertices[used], geo.vertex_normal[used],
                        np.sqrt(area[used]), rgba)
        pieces.extend(piece)
    if not pieces:
        return pieces
    return [_merge_coincident({k: np.concatenate([p[k] for p in pieces]) for k in pieces[0]})]


def _merge_coincident(arrays: dict) -> dict:
    """Merge surfels at the same position and facing the same side (vertices split at UV
    seams or by normals): areas add, normals average by area, colour of the first."""
    pos, nrm = arrays["positions"], arrays["normals"]
    side = np.sign(nrm[:, np.argmax(np.abs(nrm).sum(0))])  # keep double-sided twins apart
    key = np.concatenate([pos, side[:, None]], axis=1)
    _, first, inverse = np.unique(key, axis=0, return_index=True, return_inverse=True)
    inverse = inverse.ravel()
    if len(first) == len(pos):
        return arrays
    area = arrays["radius"].astype(np.float64) ** 2
    total = np.bincount(inverse, area)
    normal = np.zeros((len(first), 3))
    for d in range(3):
        normal[:, d] = np.bincount(inverse, nrm[:, d] * area)
    length = np.linalg.norm(normal, axis=1)
    # opposite normals at one position cancel: keep the first one's
    normal = np.where(length[:, None] > 1e-9 * total[:, None],
                      normal / np.maximum(length, 1e-300)[:, None], nrm[first])
    return {"positions": pos[first], "normals": normal, "radius": np.sqrt(total),
            "colors": arrays["colors"][first], "opacity": arrays["opacity"][first]}


def _finish(part, positions, normals, radius, rgba) -> list[dict]:
    """Apply the alpha mode and double-sidedness; arrays as Surfels.from_arrays takes them."""
    alpha = rgba[:, 3]
    if part.alpha_mode == "MASK":
        keep = alpha >= part.alpha_cutoff
        positions, normals, radius, rgba = positions[keep], normals[keep], radius[keep], rgba[keep]
        opacity = np.ones(len(positions))
    elif part.alpha_mode == "BLEND":
        # fully transparent samples cost splatting time and show nothing: left out
        keep = alpha >= MIN_OPACITY
        positions, normals, radius, rgba = positions[keep], normals[keep], radius[keep], rgba[keep]
        opacity = np.clip(rgba[:, 3], 0.0, 1.0)
    else:
        opacity = np.ones(len(positions))
    out = {"positions": positions, "normals": normals, "radius": radius,
           "colors": np.clip(rgba[:, :3], 0.0, 1.0), "opacity": opacity}
    if not part.double_sided:
        return [out]
    back = dict(out, normals=-normals)
    return [out, back]


# -- colour ------------------------------------------------------------------------------


def _colors(part: MeshPart, n: int, uv, vertex_colors, geo: _Faces) -> np.ndarray:
    """(n, 4) float64 linear RGBA: the texture or the vertex colours (or white), times the
    base colour factor. uv, vertex_colors: (n, 2), (n, 3 or 4) at the samples, or None."""
    rgba = np.ones((n, 4))
    coloured = True
    if part.texture is not None and uv is not None:
        rgba = sample_texture(mip(part.texture, _mip_level(part, geo, n)), uv)
    elif vertex_colors is not None:
        rgba[:, :vertex_colors.shape[1]] = vertex_colors
    else:
        coloured = False
    base = part.base_color
    if base is None:
        base = (1.0, 1.0, 1.0, 1.0) if coloured else DEFAULT_COLOR
    return rgba * np.asarray(base, dtype=np.float64)


def _mip_level(part: MeshPart, geo: _Faces, n_samples: int) -> int:
    """The mip level whose texels are about as far apart as the samples (box pyramid)."""
    if part.uv is None or n_samples == 0 or geo.index.size == 0:
        return 0
    t0, t1, t2 = (part.uv[part.faces[geo.index, i]] for i in range(3))
    e1, e2 = t1 - t0, t2 - t0
    uv_area = 0.5 * float(np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]).sum())
    h, w = part.texture.shape[:2]
    texels_per_sample = uv_area * w * h / n_samples
    if not (texels_per_sample > 1.0 and math.isfinite(texels_per_sample)):
        return 0
    return int(0.5 * math.log2(texels_per_sample))


def mip(texture: np.ndarray, level: int) -> np.ndarray:
    """The texture box-filtered ``level`` times by 2 x 2 (linear values; odd edges repeat)."""
    t = texture
    for _ in range(level):
        if t.shape[0] < 2 and t.shape[1] < 2:
            break
        if t.shape[0] % 2:
            t = np.concatenate([t, t[-1:]], axis=0)
        if t.shape[1] % 2:
            t = np.concatenate([t, t[:, -1:]], axis=1)
        t = 0.25 * (t[0::2, 0::2] + t[1::2, 0::2] + t[0::2, 1::2] + t[1::2, 1::2])
    return t


def sample_texture(texture: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Bilinear lookup with REPEAT wrapping: (n, C) float64 from an (H, W, C) texture.

    uv: (n, 2) with the origin at the bottom left of the image (OBJ and trimesh's convention;
    row 0 of the array is the top of the image). Texel centres sit at half-integers.
    """
    h, w = texture.shape[:2]
    uv = np.nan_to_num(np.asarray(uv, dtype=np.float64), nan=0.0, posinf=0.0, neginf=0.0)
    x = np.mod(uv[:, 0], 1.0) * w - 0.5
    y = np.mod(1.0 - uv[:, 1], 1.0) * h - 0.5
    x0, y0 = np.floor(x), np.floor(y)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    x0 = x0.astype(np.int64) % w
    y0 = y0.astype(np.int64) % h
    x1, y1 = (x0 + 1) % w, (y0 + 1) % h
    t = texture
    return ((t[y0, x0] * (1 - fx) + t[y0, x1] * fx) * (1 - fy)
            + (t[y1, x0] * (1 - fx) + t[y1, x1] * fx) * fy).astype(np.float64)


def texture_from_image(image) -> np.ndarray:
    """(H, W, 4) float32 linear RGBA from a PIL image (sRGB colour, linear alpha)."""
    rgba = np.asarray(image.convert("RGBA"), dtype=np.float32) / 255.0
    out = np.empty_like(rgba)
    out[..., :3] = srgb_to_linear(rgba[..., :3])
    out[..., 3] = rgba[..., 3]
    return out
