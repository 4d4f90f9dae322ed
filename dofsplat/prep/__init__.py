"""Data to surfels: everything between a file's points or triangles and a ``Surfels`` model.

* ``pointcloud``: bare points to surfels (normals, their orientation, radii);
* ``meshes``: triangle meshes sampled into surfels (textures, creases);
* ``normalise``: per-point weights so that a surface's splats sum to one;
* ``neighbours``: the k-nearest-neighbour and direction queries they share.

The loaders in ``dofsplat.io`` call these; rendering never does.
"""
