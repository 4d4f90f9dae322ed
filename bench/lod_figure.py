"""A Figure-5-style picture: the DOF render with LOD beside the levels it was drawn from.

For the demo plane and the lion scan (if ../shared/data is there): left, the depth-of-field
render with LOD; right, the same frame with --show-lod (each splat coloured by its level,
drawn without the blur: grey are single surfels, then blue, cyan, green, yellow, orange,
red, ... as the nodes get coarser). Writes one PNG.

    python bench/lod_figure.py docs/images/lod.png
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw

sys.path.insert(0, str(Path(__file__).resolve().parent))

import dofsplat as ds  # noqa: E402
from dofsplat.demo import plane_scene  # noqa: E402
from dofsplat.io import linear_to_srgb  # noqa: E402

SIZE = 384


def to_image(res) -> Image.Image:
    rgb = np.clip(linear_to_srgb(np.clip(res.rgb, 0, 1)), 0, 1)
    return Image.fromarray((rgb * 255 + 0.5).astype(np.uint8))


def row(surfels, camera, lens, label):
    dof = ds.render(surfels, camera, lens)
    levels = ds.render(surfels, camera, lens, ds.RenderSettings(show_lod=True))
    st = dof.stats
    text = (f"{label}: {st['splats_rendered']:,} splats of {st['points_in']:,} surfels, "
            f"{st['fragments'] / 1e6:.1f} M fragments")
    print(text)
    return [to_image(dof), to_image(levels)], text


def main(argv=None):
    argv = sys.argv[1:] if argv is None else argv
    out = Path(argv[0] if argv else "lod.png")
    rows = []
    surfels, camera, lens = plane_scene(SIZE, SIZE)
    rows.append(row(surfels, camera, ds.ThinLens(focus_distance=lens.focus_distance,
                                                  aperture=0.3), "plane, A = 0.3"))
    from table1 import LION, lion_scene

    if LION.exists():
        surfels, camera, lens = lion_scene(None, SIZE, SIZE)
        rows.append(row(surfels, camera, ds.ThinLens(focus_distance=lens.focus_distance,
                                                      aperture=1.5), "lion scan, A = 1.5"))
    pad = 22
    sheet = Image.new("RGB", (2 * SIZE, len(rows) * (SIZE + pad)), (255, 255, 255))
    draw = ImageDraw.Draw(sheet)
    for r, (images, text) in enumerate(rows):
        y = r * (SIZE + pad)
        for c, im in enumerate(images):
            sheet.paste(im, (c * SIZE, y))
        draw.text((6, y + SIZE + 5), text, fill=(0, 0, 0))
    sheet.save(out, optimize=True)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
