"""Surfels: the point-based surface as a structure of arrays.

A surfel k is a small oriented disk: a position P_k, a normal, a radius, a colour and an
opacity (paper Section 4.2, Figure 2). Its basis function r_k is a Gaussian in the tangent
plane. How the disk radius maps to the Gaussian (docs/maths.md, "Radius and variance"):

* the Gaussian's standard deviation along each tangent axis is half the disk radius,
  V_k^r = diag((r_u/2)^2, (r_v/2)^2): the disk of radius r is the Gaussian's 2-sigma
  contour, so with a cutoff c = 2.5 the kernel reaches 1.12 r;
* the surfel stands for a piece of surface of area r_u * r_v (times the optional
  per-surfel normalisation ``weight``). A regular grid of spacing h therefore wants
  r = h, and its accumulated weights sum to 1 (partition of unity, Section 6.3), which is
  what makes the accumulated weight a coverage estimate.

Elliptical surfels (for instance from 3D Gaussian splats) give a unit ``tangent`` (the
direction of the first axis, r_u = ``radius``) and ``radius_v`` for the second axis, which
is normal x tangent.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field, replace

import numpy as np

from .errors import DofsplatError


@dataclass(frozen=True)
class Material:
    """Phong material shared by all surfels of a model (Section 6.5)."""

    ambient: float = 0.15  # fraction of the surfel colour lit by ambient light
    diffuse: float = 0.85  # Lambertian fraction
    specular: float = 0.25  # white specular highlight strength
    shininess: float = 32.0  # Phong exponent

    def __post_init__(self):
        for name in ("ambient", "diffuse", "specular"):
            v = getattr(self, name)
            if not np.isfinite(v) or v < 0:
                raise DofsplatError(f"material {name} must be a finite number >= 0, got {v}")
        if not np.isfinite(self.shininess) or self.shininess <= 0:
            raise DofsplatError(f"material shininess must be > 0, got {self.shininess}")


VALIDATE_ROWS = 1 << 20  # rows that ``Surfels._validate`` checks at a time
VIEW_SAMPLE = 20_000  # the default camera's sample of a model (cli.framing.visibility_sample)


@dataclass
class Surfels:
    """A surfel model as parallel arrays (N surfels).

    positions: (N, 3) float32, world units
    normals:   (N, 3) float32, unit length (normalised at construction)
    radius:    (N,)   float32, world units, disk radius (first tangent axis for ellipses)
    colors:    (N, 3) float32, linear RGB in [0, 1]
    opacity:   (N,)   float32 in [0, 1]; 1 is opaque
    tangent:   (N, 3) float32 or None, unit first tangent axis of elliptical surfels
    radius_v:  (N,)   float32 or None, disk radius along normal x tangent
    weight:    (N,)   float32 or None, per-surfel normalisation factor on the area r_u*r_v
    material:  Phong material for the whole model
    """

    positions: np.ndarray
    normals: np.ndarray
    radius: np.ndarray
    colors: np.ndarray
    opacity: np.ndarray | None = None
    tangent: np.ndarray | None = None
    radius_v: np.ndarray | None = None
    weight: np.ndarray | None = None
    material: Material = field(default_factory=Material)

    def __post_init__(self):
        if not isinstance(self.material, Material):
            raise DofsplatError(f"material must be a Material, got {type(self.material).__name__}")
        n = _rows(self.positions, 3, "positions")
        self.positions = _floats(self.positions, "positions")
        self.normals = _floats(self.normals, "normals")
        _check_shape(self.normals, (n, 3), "normals")
        self.radius = _column(self.radius, n, "radius")
        self.colors = _floats(self.colors, "colors")
        _check_shape(self.colors, (n, 3), "colors")
        self.opacity = (np.ones(n, np.float32) if self.opacity is None
                        else _column(self.opacity, n, "opacity"))
        if (self.tangent is None) != (self.radius_v is None):
            raise DofsplatError("elliptical surfels need both 'tangent' and 'radius_v'")
        if self.tangent is not None:
            self.tangent = _floats(self.tangent, "tangent")
            _check_shape(self.tangent, (n, 3), "tangent")
            self.radius_v = _column(self.radius_v, n, "radius_v")
        if self.weight is not None:
            self.weight = _column(self.weight, n, "weight")
        self._validate()

    def __len__(self) -> int:
        return self.positions.shape[0]

    @property
    def is_elliptical(self) -> bool:
        return self.tangent is not None

    def _validate(self):
        """Check every row, and mend in place those that need it (non-unit normals and
        tangents, colours below 0, opacities outside [0, 1]), ``VALIDATE_ROWS`` rows at a
        time: the temporaries are a block's, whatever the model's size (issue 50: a model
        of memory maps is never read whole into memory)."""
        n = len(self)
        names = ["positions", "normals", "radius", "colors", "opacity", "tangent",
                 "radius_v", "weight"]
        zero_normals = parallel = 0
        non_positive = [0, 0]  # radius, radius_v
        for a in range(0, max(n, 1), VALIDATE_ROWS):
            rows = slice(a, a + VALIDATE_ROWS)
            for name in names:
                v = getattr(self, name)
                if v is not None and not np.all(np.isfinite(v[rows])):
                    raise DofsplatError("surfel arrays contain NaN or inf; use "
                                        "Surfels.from_arrays to drop such rows")
            normals = self.normals[rows]
            lengths = np.linalg.norm(normals, axis=1)
            zero_normals += int(np.count_nonzero(lengths < 1e-12))
            # rescale only rows that are not unit already: re-normalising a unit float32
            # vector can move it by an ulp, and a file's normals should survive a round
            # trip exactly
            off = np.abs(lengths - 1.0) > 1e-6
            if off.any() and not zero_normals:
                self._writable("normals")[a + np.flatnonzero(off)] /= lengths[off, None]
            non_positive[0] += int(np.count_nonzero(self.radius[rows] <= 0))
            if self.radius_v is not None:
                non_positive[1] += int(np.count_nonzero(self.radius_v[rows] <= 0))
            if self.tangent is not None and not zero_normals:
                # project the tangent into the surfel's plane and normalise it
                normals = self.normals[rows]
                t64 = self.tangent[rows].astype(np.float64)
                t = t64 - np.sum(t64 * normals, 1)[:, None] * normals
                tl = np.linalg.norm(t, axis=1)
                parallel += int(np.count_nonzero(tl < 1e-9))
                # as for normals: leave tangents that are unit and in the plane untouched
                off = ((np.abs(np.linalg.norm(t64, axis=1) - 1.0) > 1e-6)
                       | (np.abs(tl - 1.0) > 1e-6))
                if off.any() and not parallel:
                    self._writable("tangent")[a + np.flatnonzero(off)] = (
                        t[off] / tl[off, None]).astype(np.float32)
            if np.any(self.colors[rows] < 0.0):
                colors = self._writable("colors")
                np.clip(colors[rows], 0.0, None, out=colors[rows])
            opacity = self.opacity[rows]
            if np.any((opacity < 0.0) | (opacity > 1.0)):
                opacity = self._writable("opacity")
                np.clip(opacity[rows], 0.0, 1.0, out=opacity[rows])
            if self.weight is not None and np.any(self.weight[rows] < 0):
                raise DofsplatError("surfel normalisation weights must be >= 0")
        if zero_normals:
            raise DofsplatError(f"{zero_normals} of {n} surfels have a zero-length normal")
        if max(non_positive):
            raise DofsplatError(f"{max(non_positive)} of {n} surfels have a radius <= 0")
        if parallel:
            raise DofsplatError(f"{parallel} of {n} elliptical surfels have a tangent "
                                "parallel to their normal")

    def _writable(self, name: str) -> np.ndarray:
        """The array ``name``, copied first where it cannot be written (a prepared model's
        read-only memory map): ``_validate`` mends rows in place, and only where some row
        needs it, so that a valid file's maps are neither written nor copied."""
        a = getattr(self, name)
        if not a.flags.writeable:
            a = np.array(a)
            setattr(self, name, a)
        return a

    @classmethod
    def from_arrays(cls, positions, normals, radius, colors, opacity=None, *,
                    tangent=None, radius_v=None, weight=None,
                    material: Material | None = None, source: str = "input") -> "Surfels":
        """Build surfels from raw arrays, dropping rows with NaN or inf (with one warning).

        Zero-length normals and non-positive radii are errors, not dropped: they mean the
        data is wrong, not merely incomplete.
        """
        n = _rows(positions, 3, "positions")
        arrays = {"positions": positions, "normals": normals, "radius": radius,
                  "colors": colors, "opacity": opacity, "tangent": tangent,
                  "radius_v": radius_v, "weight": weight}
        arrays = {k: (None if v is None else _floats(v, k)) for k, v in arrays.items()}
        arrays = {k: (np.full(n, v) if v is not None and v.ndim == 0 else v)  # as Surfels does
                  for k, v in arrays.items()}
        keep = np.ones(n, bool)
        for k, a in arrays.items():
            if a is None:
                continue
            if a.shape[0] != n:
                raise DofsplatError(f"{k} has {a.shape[0]} rows but positions has {n}")
            keep &= np.all(np.isfinite(a.reshape(n, -1)), axis=1)
        dropped = n - int(keep.sum())
        if dropped:
            warnings.warn(f"{source}: dropped {dropped} of {n} surfels with NaN or inf values",
                          stacklevel=2)
            arrays = {k: (None if v is None else v[keep]) for k, v in arrays.items()}
        if not keep.any():
            raise DofsplatError(f"{source}: no valid surfels (all {n} rows had NaN or inf)")
        return cls(**arrays, material=material or Material())

    @classmethod
    def stored(cls, positions, normals, radius, colors, opacity, tangent=None, radius_v=None,
               weight=None, material: Material | None = None) -> "Surfels":
        """Surfels from arrays that were checked when they were stored (``io.model_file``):
        taken as they are, memory maps included, without the checks and copies of
        ``Surfels(...)``, which would read every page of a file larger than memory."""
        surfels = cls.__new__(cls)
        surfels.positions, surfels.normals, surfels.radius, surfels.colors = (
            positions, normals, radius, colors)
        surfels.opacity, surfels.tangent, surfels.radius_v, surfels.weight = (
            opacity, tangent, radius_v, weight)
        surfels.material = material or Material()
        return surfels

    def remember_bounds(self, bounds, view_bounds) -> None:
        """Keep ``bounds()`` and ``view_bounds()`` as known (a stored model's header holds
        them), for these positions: nothing is read to answer them."""
        box = lambda pair: tuple(np.asarray(v, np.float32) for v in pair)  # noqa: E731
        self.__dict__["_known_bounds"] = (self.positions, box(bounds), box(view_bounds))

    def sample(self, k: int) -> "Surfels":
        """At most k of the surfels, drawn at random, seeded (the same model gives the same
        sample), in their order; the model itself where it has k or fewer. A stored model
        (``io.model_file``: its rows in another order, its arrays on disk) gives the sample
        of the model it was prepared from, which its file keeps: what is made of it (the
        default camera's direction) is that model's, and nothing of the file is read."""
        known = self.__dict__.get("_known_sample")
        if known is not None and known[0] is self.positions and known[1] == k:
            return known[2]
        n = len(self)
        if n <= k:
            return self
        return self.subset(np.sort(np.random.default_rng(0).choice(n, k, replace=False)))

    def remember_sample(self, k: int, sample: "Surfels") -> None:
        """Keep ``sample(k)``'s answer for these positions (a stored model's file holds it)."""
        self.__dict__["_known_sample"] = (self.positions, k, sample)

    def _known(self, which: int):
        known = self.__dict__.get("_known_bounds")
        return known[which] if known is not None and known[0] is self.positions else None

    def subset(self, index) -> "Surfels":
        """The surfels selected by a boolean mask or an index array."""
        pick = lambda a: None if a is None else a[index]  # noqa: E731
        return replace(self, positions=self.positions[index], normals=self.normals[index],
                       radius=self.radius[index], colors=self.colors[index],
                       opacity=self.opacity[index], tangent=pick(self.tangent),
                       radius_v=pick(self.radius_v), weight=pick(self.weight))

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Axis-aligned bounding box (lo, hi) of the positions, world units."""
        known = self._known(1)
        if known is not None:
            return known
        return self.positions.min(axis=0), self.positions.max(axis=0)

    def view_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """``bounds``, widened by the largest disk radius where the box is smaller than
        that disk (one surfel, or all at one point): the box a default camera frames. A lone
        surfel's box is a point, and the camera framing it stood 3e-9 units from it."""
        known = self._known(2)
        if known is not None:
            return known
        lo, hi = self.bounds()
        r = float(np.max(self.radius))
        if self.radius_v is not None:
            r = max(r, float(np.max(self.radius_v)))
        if 0.5 * float(np.linalg.norm(hi.astype(np.float64) - lo)) < r:  # (float32 overflows)
            lo, hi = lo - r, hi + r
        return lo, hi


def concatenate(parts: list[Surfels]) -> Surfels:
    """Join several models into one (material of the first; weights default to 1)."""
    if not parts:
        raise DofsplatError("nothing to concatenate")
    ell = any(p.is_elliptical for p in parts)
    wgt = any(p.weight is not None for p in parts)

    def cat(get):
        return np.concatenate([get(p) for p in parts])

    def frame(p):
        if p.is_elliptical:
            return p.tangent, p.radius_v
        return tangent_frame(p.normals)[0], p.radius

    return Surfels(
        positions=cat(lambda p: p.positions), normals=cat(lambda p: p.normals),
        radius=cat(lambda p: p.radius), colors=cat(lambda p: p.colors),
        opacity=cat(lambda p: p.opacity),
        tangent=cat(lambda p: frame(p)[0]) if ell else None,
        radius_v=cat(lambda p: frame(p)[1]) if ell else None,
        weight=cat(lambda p: p.weight if p.weight is not None
                   else np.ones(len(p), np.float32)) if wgt else None,
        material=parts[0].material)


def tangent_frame(normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit tangents (t_u, t_v) perpendicular to unit normals, (N, 3) each.

    The same construction as the kernels' scalar version (splat/ewa.py): cross the normal
    with the world axis it is least aligned with.
    """
    n = np.asarray(normals, dtype=np.float64)
    helper = np.zeros_like(n)
    ax = np.argmin(np.abs(n), axis=1)
    helper[np.arange(len(n)), ax] = 1.0
    tu = np.cross(n, helper)
    tu /= np.linalg.norm(tu, axis=1)[:, None]
    tv = np.cross(n, tu)
    return tu.astype(np.float32), tv.astype(np.float32)


def _rows(a, cols, name) -> int:
    a = np.asarray(a)
    if a.ndim != 2 or a.shape[1] != cols:
        raise DofsplatError(f"{name} must have shape (N, {cols}), got {a.shape}")
    if a.shape[0] == 0:
        raise DofsplatError(f"{name} is empty: a model needs at least one surfel")
    return a.shape[0]


def _check_shape(a, shape, name):
    if a.shape != shape:
        raise DofsplatError(f"{name} must have shape {shape}, got {a.shape}")


def _floats(a, name) -> np.ndarray:
    """``a`` as a C-contiguous float32 array (a scalar stays 0-d, as ascontiguousarray
    would not keep it); a DofsplatError naming it when it is not numbers."""
    try:
        a = np.asarray(a, dtype=np.float32)
    except (TypeError, ValueError):
        got = repr(a) if isinstance(a, str) else type(a).__name__
        raise DofsplatError(f"{name} must be numbers, got {got[:60]}") from None
    return a if a.ndim == 0 else np.ascontiguousarray(a)


def _column(a, n, name) -> np.ndarray:
    a = _floats(a, name)
    if a.ndim == 0:  # one value for every surfel
        a = np.full(n, a, np.float32)
    if a.shape != (n,):
        raise DofsplatError(f"{name} must have shape ({n},), got {a.shape}")
    return a
