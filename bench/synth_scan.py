"""A synthetic aerial-and-street scan of any size, for the out-of-core work (issue 50, item 5).

    python bench/synth_scan.py OUT.las --points 20000000 [--seed 1] [--density 40] [--laz]

No billion-point scan fits in the repository, so this writes one: a square of terrain (value
noise over four octaves, from 512 m hills to 8 m bumps), buildings (boxes 8-30 m wide and
5-40 m high, roofs sampled at the scan's density and walls at a third of it) and trees (a
trunk and an ellipsoidal crown), with colour (grass and soil, roof tiles and concrete,
facades, leaves), intensity and the LAS classes a classified scan carries (2 ground, 6
building, 5 high vegetation). It is made cell by cell (CELL x CELL metres), each cell from its
own random stream (the seed and the cell's indices), and the terrain is one function of the
position, so the cells join without seams, the same seed gives the same file byte for byte,
and memory holds one cell whatever the size (about DENSITY x CELL^2 x 1.3 points). The side
of the square is chosen for --points at --density points per square metre (the count
written is within a few per cent of it: each cell draws its own). The coordinates are
UTM-like (500 km east, 4,000 km north, millimetre scale), as a surveyor's file is.

In Python: ``generate(path, points, seed=1, density=40.0)`` writes the file and returns its
point count; ``cells(points, seed, density)`` yields each cell's arrays without writing.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np

CELL = 64.0  # metres: the side of a cell, generated at once
ORIGIN = (500_000.0, 4_000_000.0, 0.0)  # the square's south-west corner, UTM-like
SCALE = 0.001  # the LAS file's coordinate quantum (mm)
GROUND, VEGETATION, BUILDING = 2, 5, 6  # LAS classes
OCTAVES = ((512.0, 18.0), (128.0, 5.0), (32.0, 1.2), (8.0, 0.25))  # (wavelength m, amplitude m)


# -- the terrain: value noise, one function of the position --------------------------------


def _lattice(ix: np.ndarray, iy: np.ndarray, seed: int, octave: int) -> np.ndarray:
    """A value in [0, 1) per integer lattice point: a hash of (ix, iy, seed, octave)."""
    salt = np.uint64(((seed * 1_000_003 + octave) * 0x165667B19E3779F9) & 0xFFFFFFFFFFFFFFFF)
    with np.errstate(over="ignore"):  # the hash wraps modulo 2^64 by design
        h = (ix.astype(np.uint64) * np.uint64(0x9E3779B97F4A7C15)
             ^ iy.astype(np.uint64) * np.uint64(0xC2B2AE3D27D4EB4F) ^ salt)
        h ^= h >> np.uint64(33)
        h *= np.uint64(0xFF51AFD7ED558CCD)
        h ^= h >> np.uint64(33)
    return (h >> np.uint64(11)).astype(np.float64) / float(1 << 53)


def terrain(x: np.ndarray, y: np.ndarray, seed: int) -> np.ndarray:
    """The ground's height (m) at (x, y) (metres from the square's corner): smoothstep-
    interpolated value noise, OCTAVES summed. Defined everywhere, so cells join exactly."""
    z = np.zeros(np.shape(x))
    for octave, (wavelength, amplitude) in enumerate(OCTAVES):
        u, v = np.asarray(x) / wavelength, np.asarray(y) / wavelength
        i, j = np.floor(u).astype(np.int64), np.floor(v).astype(np.int64)
        fu, fv = u - i, v - j
        su, sv = fu * fu * (3 - 2 * fu), fv * fv * (3 - 2 * fv)
        a, b = _lattice(i, j, seed, octave), _lattice(i + 1, j, seed, octave)
        c, d = _lattice(i, j + 1, seed, octave), _lattice(i + 1, j + 1, seed, octave)
        z += amplitude * ((a + (b - a) * su) * (1 - sv) + (c + (d - c) * su) * sv)
    return z


# -- one cell -----------------------------------------------------------------------------


EXTRA = 1.55  # all points over the ground's (roofs, walls, crowns): 1.57 measured at 2 M points


def square_side(points: int, density: float) -> float:
    """The side (m) of the square that holds about ``points`` at ``density`` per m^2 of
    ground (buildings and trees add about half as many again, EXTRA, counted in)."""
    return math.sqrt(points / (density * EXTRA))


def cell_points(seed: int, cx: int, cy: int, density: float) -> dict[str, np.ndarray]:
    """The points of cell (cx, cy): x y z (metres from the square's corner, float64),
    red green blue (uint16), intensity (uint16), classification (uint8)."""
    rng = np.random.default_rng([seed, cx, cy])
    x0, y0 = cx * CELL, cy * CELL
    parts = []
    # buildings: 0-2 boxes per cell, kept inside it, one base height (the ground at its centre)
    footprints = []
    for _ in range(rng.integers(0, 3)):
        w, d = rng.uniform(8.0, 30.0, 2)
        bx, by = x0 + rng.uniform(0, CELL - w), y0 + rng.uniform(0, CELL - d)
        if any(bx < fx + fw and fx < bx + w and by < fy + fd and fy < by + d
               for fx, fy, fw, fd, _, _ in footprints):
            continue
        base = float(terrain(np.array([bx + w / 2]), np.array([by + d / 2]), seed)[0])
        footprints.append((bx, by, w, d, base, rng.uniform(5.0, 40.0)))
    for bx, by, w, d, base, height in footprints:
        n = rng.poisson(density * w * d)  # the roof, slightly pitched
        rx, ry = bx + rng.uniform(0, w, n), by + rng.uniform(0, d, n)
        rz = base + height + 0.15 * np.minimum(ry - by, by + d - ry)
        tone = rng.choice([[150, 60, 45], [110, 110, 115], [70, 70, 75]])
        parts.append(_part(rng, rx, ry, rz, tone, 18, BUILDING))
        perimeter = 2 * (w + d)
        n = rng.poisson(density / 3 * perimeter * height)  # the walls
        t = rng.uniform(0, perimeter, n)
        wx = np.where(t < w, bx + t, np.where(t < w + d, bx + w,
                      np.where(t < 2 * w + d, bx + (2 * w + d - t), bx)))
        wy = np.where(t < w, by, np.where(t < w + d, by + (t - w),
                      np.where(t < 2 * w + d, by + d, by + (perimeter - t))))
        wz = base + rng.uniform(0, height, n)
        parts.append(_part(rng, wx, wy, wz, [200, 185, 160], 14, BUILDING))
    # the ground, but under the buildings
    n = rng.poisson(density * CELL * CELL)
    gx, gy = x0 + rng.uniform(0, CELL, n), y0 + rng.uniform(0, CELL, n)
    keep = np.ones(n, bool)
    for bx, by, w, d, _, _ in footprints:
        keep &= ~((gx >= bx) & (gx < bx + w) & (gy >= by) & (gy < by + d))
    gx, gy = gx[keep], gy[keep]
    grass = _lattice(np.floor(gx / 6).astype(np.int64), np.floor(gy / 6).astype(np.int64),
                     seed, 99)[:, None]
    tone = grass * np.array([70, 120, 50]) + (1 - grass) * np.array([125, 105, 80])
    parts.append(_part(rng, gx, gy, terrain(gx, gy, seed), tone, 10, GROUND))
    # trees: 4-16 per cell, off the buildings
    for _ in range(rng.integers(4, 17)):
        tx, ty = x0 + rng.uniform(3, CELL - 3), y0 + rng.uniform(3, CELL - 3)
        if any(bx - 3 < tx < bx + w + 3 and by - 3 < ty < by + d + 3
               for bx, by, w, d, _, _ in footprints):
            continue
        ground = float(terrain(np.array([tx]), np.array([ty]), seed)[0])
        trunk, radius = rng.uniform(2.0, 5.0), rng.uniform(2.0, 6.0)
        n = rng.poisson(density * 3.0 * math.pi * radius * radius)  # the crown's surface
        direction = rng.normal(size=(n, 3))
        direction /= np.linalg.norm(direction, axis=1, keepdims=True)
        r = radius * rng.uniform(0.85, 1.0, (n, 1))
        crown = np.array([tx, ty, ground + trunk + radius * 0.8]) + direction * r * [1, 1, 0.8]
        parts.append(_part(rng, crown[:, 0], crown[:, 1], crown[:, 2], [45, 95, 40], 25,
                           VEGETATION))
        n = rng.poisson(density * 2.0 * math.pi * 0.3 * trunk)
        a = rng.uniform(0, 2 * math.pi, n)
        parts.append(_part(rng, tx + 0.3 * np.cos(a), ty + 0.3 * np.sin(a),
                           ground + rng.uniform(0, trunk, n), [90, 70, 50], 10, VEGETATION))
    return {key: np.concatenate([p[key] for p in parts]) for key in parts[0]}


def _part(rng, x, y, z, tone, spread: float, klass: int) -> dict[str, np.ndarray]:
    """Points of one kind: their colour about tone (8-bit sRGB, +- spread), stored 16-bit;
    their intensity from the colour's brightness, with noise."""
    n = len(x)
    rgb = np.clip(np.asarray(tone, np.float64) + rng.normal(0, spread, (n, 3)), 0, 255)
    intensity = np.clip(rgb.mean(axis=1) * 200 + rng.normal(0, 800, n), 0, 65535)
    return {"x": np.asarray(x, np.float64), "y": np.asarray(y, np.float64),
            "z": np.asarray(z, np.float64), "rgb": (rgb * 257).astype(np.uint16),
            "intensity": intensity.astype(np.uint16),
            "classification": np.full(n, klass, np.uint8)}


def cells(points: int, seed: int = 1, density: float = 40.0):
    """Each cell's points (``cell_points``), row by row over the square for ``points``; the
    last row and column of cells cut at the square's side."""
    side = square_side(points, density)
    n = max(1, math.ceil(side / CELL))
    for cy in range(n):
        for cx in range(n):
            cell = cell_points(seed, cx, cy, density)
            if (cx + 1) * CELL > side or (cy + 1) * CELL > side:
                inside = (cell["x"] < side) & (cell["y"] < side)
                cell = {key: value[inside] for key, value in cell.items()}
            yield cell


def generate(path, points: int, seed: int = 1, density: float = 40.0,
             progress: bool = False) -> int:
    """Write the scan to path (.las, or .laz with laspy's lazrs) and return its point count.
    Written to a temporary name and renamed: an interrupted run leaves no file."""
    import laspy

    path = Path(path)
    header = laspy.LasHeader(point_format=3, version="1.2")
    header.offsets = np.array(ORIGIN)
    header.scales = np.array([SCALE] * 3)
    tmp = path.with_name(".part-" + path.name)  # the suffix kept: .laz is compressed
    total = 0
    n_cells = max(1, math.ceil(square_side(points, density) / CELL)) ** 2
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=n_cells, unit="cell", desc=f"synthetic scan -> {path.name}")
    try:
        with laspy.open(str(tmp), mode="w", header=header) as writer:
            for cell in cells(points, seed, density):
                record = laspy.ScaleAwarePointRecord.zeros(len(cell["x"]), header=header)
                record.x = cell["x"] + ORIGIN[0]
                record.y = cell["y"] + ORIGIN[1]
                record.z = cell["z"] + ORIGIN[2]
                record.red, record.green, record.blue = cell["rgb"].T
                record.intensity = cell["intensity"]
                record.classification = cell["classification"]
                writer.write_points(record)
                total += len(cell["x"])
                if bar is not None:
                    bar.update(1)
        tmp.replace(path)
    finally:
        if bar is not None:
            bar.close()
        tmp.unlink(missing_ok=True)
    return total


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", type=Path, help="the .las (or .laz) file to write")
    ap.add_argument("--points", type=float, default=1e6, help="about this many points")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--density", type=float, default=40.0, help="points per square metre")
    args = ap.parse_args(argv)
    t = time.perf_counter()
    n = generate(args.out, int(args.points), args.seed, args.density, progress=True)
    s = time.perf_counter() - t
    size = args.out.stat().st_size
    print(f"{args.out}: {n:,} points in {s:.1f} s ({n / s / 1e6:.2f} M points/s), "
          f"{size / n:.1f} bytes a point", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
