"""A LAS/LAZ scan as a binary PLY point cloud (x y z doubles, 8-bit red green blue), written a
million points at a time: the same points in the other format that dofsplat prepares on
disk (issue 50; bench/RESULTS.md, "The cloud on disk").

    python bench/las_to_ply.py /tmp/synth4m.laz /tmp/synth4m.ply
    /usr/bin/time -v dofsplat prepare /tmp/synth4m.ply -o X.dofsplat --on-disk on --no-cache

The coordinates are shifted by the rounded centre of the header's bounds (a PLY has no
offset of its own, and float64 keeps them either way); colours keep their top 8 bits.
"""

from __future__ import annotations

import argparse
import os

import numpy as np


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("input", help="a .las or .laz file")
    parser.add_argument("output", help="the .ply file to write")
    args = parser.parse_args()

    import laspy

    with laspy.open(args.input) as reader:
        header = reader.header
        n = int(header.point_count)
        rgb = {"red", "green", "blue"} <= set(header.point_format.dimension_names)
        centre = np.round(0.5 * (np.asarray(header.mins) + np.asarray(header.maxs)))
        wide = rgb and max(int(np.max(np.asarray(p[c]))) for p in reader.chunk_iterator(1 << 20)
                           for c in ("red", "green", "blue")) > 255
    fields = [("x", "<f8"), ("y", "<f8"), ("z", "<f8")]
    if rgb:
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    lines = ["ply", "format binary_little_endian 1.0", f"element vertex {n}"]
    lines += [f"property {'double' if t == '<f8' else 'uchar'} {name}" for name, t in fields]
    part = args.output + ".part"
    with laspy.open(args.input) as reader, open(part, "wb") as out:
        out.write(("\n".join(lines + ["end_header"]) + "\n").encode("ascii"))
        for points in reader.chunk_iterator(1 << 20):
            v = np.zeros(len(points), fields)
            for axis, name in enumerate("xyz"):
                v[name] = np.asarray(getattr(points, name)) - centre[axis]
            if rgb:
                for name in ("red", "green", "blue"):
                    c = np.asarray(points[name])
                    v[name] = (c >> 8) if wide else c
            out.write(v.tobytes())
    os.replace(part, args.output)
    print(f"wrote {args.output}: {n:,} points")


if __name__ == "__main__":
    main()
