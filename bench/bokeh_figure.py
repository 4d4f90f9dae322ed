"""The README's bokeh figure: the same defocused highlights as a disc, a 6-blade hexagon and
the paper's Gaussian, side by side (docs/images/bokeh.png).

    python bench/bokeh_figure.py [--out docs/images/bokeh.png]

The scene: a few small bright surfels ("fairy lights") well behind the focal plane, over a
dark textured plane, the lens focused in front of them.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import dofsplat as ds  # noqa: E402
from dofsplat.demo import textured_plane  # noqa: E402
from dofsplat.io import write_image  # noqa: E402
from dofsplat.surfels import concatenate  # noqa: E402


def lights(n: int = 7) -> ds.Surfels:
    rng = np.random.default_rng(3)
    pos = np.stack([np.linspace(-1.2, 1.2, n), 0.35 + 0.25 * rng.uniform(-1, 1, n),
                    np.full(n, -2.0)], axis=1)
    cols = np.array([[1.0, 0.8, 0.4], [0.5, 0.8, 1.0], [1.0, 0.5, 0.6]])[np.arange(n) % 3] * 25
    return ds.Surfels(positions=pos, normals=np.tile([0.0, 0.0, 1.0], (n, 1)),
                      radius=np.full(n, 0.03), colors=cols)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="docs/images/bokeh.png")
    ap.add_argument("--size", type=int, default=320, help="height of each panel, px")
    args = ap.parse_args(argv)
    floor = textured_plane(256, 4.0, center=(0.0, -0.2, -1.0))
    floor = ds.Surfels(positions=floor.positions, normals=floor.normals, radius=floor.radius,
                       colors=floor.colors * 0.08)
    scene = concatenate([floor, lights()])
    h = args.size
    cam = ds.Camera(eye=(0.0, 0.5, 2.5), target=(0.0, 0.3, -2.0), width=h, height=h, fov_y=40)
    panels = []
    for kw in (dict(), dict(blades=6, blade_rotation=90.0), dict(bokeh="gaussian")):
        lens = ds.ThinLens(focus_distance=2.0, aperture=0.35, **kw)
        img = ds.render(scene, cam, lens, ds.RenderSettings(shading="none")).image
        panels.append(img)
    gap = np.ones((h, 4, 4), np.float32)
    strip = np.concatenate([panels[0], gap, panels[1], gap, panels[2]], axis=1)
    write_image(Path(args.out), strip)
    print(f"wrote {args.out}: disc | 6 blades | the paper's Gaussian")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
