"""Content hashes (dofsplat.fingerprint): what a given LOD tree is checked against, and what a
sequence's folder records (tests/test_animate.py checks the folders)."""

from __future__ import annotations

import re
from dataclasses import fields, replace

import numpy as np
import pytest

import dofsplat as ds
from dofsplat.fingerprint import content_hash
from dofsplat.lod import build_hierarchy, fingerprint, hierarchy_for

from conftest import front_camera, grid_surfels


def _surfels(n=64, seed=0):
    rng = np.random.default_rng(seed)
    t = np.cross(rng.normal(size=(n, 3)), (0.0, 0.0, 1.0))
    return ds.Surfels(positions=rng.normal(size=(n, 3)), normals=np.tile((0.0, 0.0, 1.0), (n, 1)),
                      radius=rng.uniform(0.01, 0.02, n), colors=rng.uniform(0, 1, (n, 3)),
                      opacity=rng.uniform(0.5, 1, n), tangent=t,
                      radius_v=rng.uniform(0.01, 0.02, n), weight=rng.uniform(0.9, 1.1, n))


def _changed(value):
    """The same field with one number changed (a Material: one coefficient)."""
    if isinstance(value, np.ndarray):
        out = value.copy()
        out.reshape(-1)[out.size // 2 + 1] += np.float32(0.25)  # (not a quaternion's w)
        return out
    return replace(value, specular=value.specular + 0.25)


def test_the_hash_covers_every_field_of_a_surfel_model():
    """Equal content in other objects hashes alike; one number changed in any field (every
    array, the material) changes it."""
    s = _surfels()
    h = content_hash(s)
    assert re.fullmatch("[0-9a-f]{32}", h)
    assert content_hash(replace(s, **{f.name: getattr(s, f.name) for f in fields(s)})) == h
    copy = ds.Surfels(**{f.name: (lambda v: v.copy() if isinstance(v, np.ndarray) else v)(
        getattr(s, f.name)) for f in fields(s)})
    assert content_hash(copy) == h
    seen = {h}
    for f in fields(s):
        edited = replace(s, **{f.name: _changed(getattr(s, f.name))})
        seen.add(content_hash(edited))
    assert len(seen) == len(fields(s)) + 1  # each edit its own hash
    assert content_hash(replace(s, weight=None)) not in seen


def test_the_hash_takes_any_dataclass_of_arrays():
    """Gaussians (and any dataclass of arrays): every array field counts, in field order; a
    non-contiguous array hashes as its contiguous copy; the class's name counts."""
    from dataclasses import dataclass

    from dofsplat.gaussians import Gaussians

    rng = np.random.default_rng(1)
    n = 10
    g = Gaussians(positions=rng.normal(size=(n, 3)), scales=rng.uniform(0.1, 1, (n, 3)),
                  rotations=np.tile((1.0, 0.0, 0.0, 0.0), (n, 1)),
                  opacity=rng.uniform(0.1, 1, n), sh=rng.normal(size=(n, 4, 3)))
    h = content_hash(g)
    hashes = {h} | {content_hash(replace(g, **{f.name: _changed(getattr(g, f.name))}))
                    for f in fields(g)}
    assert len(hashes) == len(fields(g)) + 1

    @dataclass
    class Pair:
        a: np.ndarray
        b: np.ndarray

    x = np.arange(12, dtype=np.float32).reshape(3, 4)
    assert content_hash(Pair(x[:, ::2], x)) == content_hash(Pair(x[:, ::2].copy(), x))
    assert content_hash(Pair(x, x)) != content_hash(Pair(x.reshape(4, 3), x))  # the shape counts
    assert content_hash(Pair(x, x)) != content_hash(Pair(x.astype(np.float64), x))
    with pytest.raises(TypeError, match="needs a dataclass instance"):
        content_hash(x)


def test_a_kept_hash_follows_arrays_assigned_anew_not_edits_in_place():
    s = _surfels()
    h = content_hash(s, cached=True)
    assert content_hash(s, cached=True) == h
    s.colors = s.colors.copy()
    s.colors[0] = 0.0
    assert content_hash(s, cached=True) != h  # a new array: hashed again
    h2 = content_hash(s, cached=True)
    s.colors[1] = 0.0  # in place: the kept hash does not see it, a fresh one does
    assert content_hash(s, cached=True) == h2
    assert content_hash(s) != h2


def test_the_trees_fingerprint_is_the_content_hash_of_what_it_reads():
    """The tree reads every surfel array but not the material: a new material keeps it."""
    s = _surfels()
    assert fingerprint(s) == build_hierarchy(s).fingerprint
    assert fingerprint(replace(s, material=ds.Material(specular=0.5))) == fingerprint(s)
    assert fingerprint(replace(s, opacity=_changed(s.opacity))) != fingerprint(s)


def _two_grids():
    """Two 32 x 32 grids, as many surfels at the same positions, other colours."""
    return grid_surfels(n=32, color=(0.8, 0.2, 0.1)), grid_surfels(n=32, color=(0.1, 0.2, 0.9))


# blurred enough that the cut draws inner nodes (256 splats of 1024): their colours are the
# tree's
LENS = ds.ThinLens(focus_distance=6.0, aperture=0.5)


def test_render_refuses_another_models_tree():
    """A tree built for another model (a 32 x 32 grid of another colour: as many surfels)
    drew that model's nodes without a word (0.8 off here); now a DofsplatError. One of
    another count was refused already; the model's own tree draws what none given draws."""
    a, b = _two_grids()
    cam, lens = front_camera(48, 48), LENS
    with pytest.raises(ds.DofsplatError) as error:
        ds.render(a, cam, lens, hierarchy=build_hierarchy(b))
    assert str(error.value) == (
        "the LOD hierarchy was built for another model of as many surfels (1024; its "
        "fingerprint differs): build it for this one (dofsplat.lod.build_hierarchy) or pass "
        "none")
    with pytest.raises(ds.DofsplatError, match="^the LOD hierarchy was built for 900 surfels, "
                                               "the model has 1024$"):
        ds.render(a, cam, lens, hierarchy=build_hierarchy(grid_surfels(n=30)))
    own = ds.render(a, cam, lens, hierarchy=build_hierarchy(a)).image
    np.testing.assert_array_equal(own, ds.render(a, cam, lens).image)


def test_a_kept_tree_is_built_again_for_arrays_assigned_anew():
    """``render`` keeps the model's tree on it: colours assigned anew (as many surfels)
    drew the old tree's node colours; now the tree is built again, and the frame is a
    fresh model's."""
    a, b = _two_grids()
    cam, lens = front_camera(48, 48), LENS
    before = ds.render(a, cam, lens)
    assert before.stats["splats_selected"] < len(a) // 2  # inner nodes drawn
    old = hierarchy_for(a)
    a.colors = b.colors
    frame = ds.render(a, cam, lens).image
    assert hierarchy_for(a) is not old
    np.testing.assert_array_equal(frame, ds.render(replace(a), cam, lens).image)
    assert np.abs(frame - before.image).max() > 0.5  # the old tree's colours are gone
