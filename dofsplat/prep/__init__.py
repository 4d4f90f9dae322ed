"""Data to surfels: everything between a file's points or triangles and a ``Surfels`` model.

* ``pointcloud``: bare points to surfels (normals, their orientation, radii);
* ``chunks``: the same for a cloud larger than a chunk, chunk by chunk with halos (bounded
  memory; on Dask workers too), and ``rules``, the decisions both take;
* ``cloudfile``: a cloud larger than memory, on disk in chunks in a work folder, which
  ``chunks`` prepares from there; ``duplicates``: the merge of points at one position;
* ``meshes``: triangle meshes sampled into surfels (textures, creases);
* ``normalise``: per-point weights so that a surface's splats sum to one;
* ``neighbours``: the k-nearest-neighbour and direction queries they share.

The loaders in ``dofsplat.io`` call these; rendering never does.
"""

# Seconds a cold first run spends compiling the preparation kernels of a point cloud
# (normals, radii) and of a mesh (sampling), each with the object-space normalisation's
# kernel, which compile apart from the renderer's (measured on the developers' 2-core
# machine, shared: README, "numba")
PREP_COMPILE_SECONDS = {"point-cloud": 8, "mesh": 4}


def kernels_compiled(kind: str) -> bool:
    """Whether numba's disk cache holds the preparation kernels of a "point-cloud" or a
    "mesh" (PREP_COMPILE_SECONDS): its own kernel and the object-space normalisation's."""
    from ..backends.cpu import kernel_cached
    from . import normalise

    if kind == "point-cloud":
        from .pointcloud import _pca_kernel as kernel
    elif kind == "mesh":
        from .meshes import _eliminate as kernel
    else:
        raise ValueError(f"unknown preparation {kind!r}")
    return kernel_cached(kernel) and kernel_cached(normalise._object_sums_kernel)

