"""The Octree: building from grids, geometry, query and check_integrity, against slow references."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from plenoctree import Octree, TreeFormatError
from plenoctree.octree import dense_tree, parse_data_format, tree_from_grid


# ---------------------------------------------------------------------- slow references
def ref_leaf_count(mask: np.ndarray) -> int:
    """Leaves of the tree built from ``mask``: recursive, one region at a time."""
    res = mask.shape[0]

    def count(x: int, y: int, z: int, size: int) -> int:      # a node covering size^3 cells
        half = size // 2
        total = 0
        for dx in (0, half):
            for dy in (0, half):
                for dz in (0, half):
                    if half == 1 or not mask[x + dx:x + dx + half, y + dy:y + dy + half,
                                             z + dz:z + dz + half].any():
                        total += 1
                    else:
                        total += count(x + dx, y + dy, z + dz, half)
        return total

    return count(0, 0, 0, res)


def ref_valid(child: np.ndarray, depth_limit: int) -> bool:
    """Whether ``child`` is a tree with positive offsets, walking it node by node."""
    n = child.shape[0]
    seen = {0}
    stack = [(0, 0)]
    while stack:
        node, depth = stack.pop()
        if depth > depth_limit:
            return False
        for off in child[node].reshape(-1).tolist():
            if off < 0:
                return False
            if off == 0:
                continue
            target = node + off
            if target >= n or target in seen:
                return False
            seen.add(target)
            stack.append((target, depth + 1))
    return len(seen) == n


def random_grid(rng, res, p, dim=4):
    mask = rng.random((res, res, res)) < p
    values = rng.normal(size=(res, res, res, dim)).astype(np.float32)
    values[..., -1] = np.abs(values[..., -1])
    return values, mask


def cell_of(points, center, radius, res):
    """Grid index of the cell containing each world point (closed far faces)."""
    u = (points - (np.asarray(center) - radius)) / (2 * np.asarray(radius)) * res
    return np.clip(np.floor(u).astype(int), 0, res - 1)


# ---------------------------------------------------------------------- from_grid
@pytest.mark.parametrize("res,p,seed", [(2, 0.5, 0), (4, 0.1, 1), (8, 0.02, 2), (16, 0.01, 3),
                                        (16, 0.3, 4), (32, 0.002, 5)])
def test_from_grid_query_matches_grid(res, p, seed):
    rng = np.random.default_rng(seed)
    values, mask = random_grid(rng, res, p)
    center, radius = np.array([0.3, -0.2, 1.0]), np.array([1.0, 2.0, 0.5])
    tree = Octree.from_grid(values, mask, center, radius, "RGBA")
    tree.check_integrity()
    assert tree.depth_limit == res.bit_length() - 2
    assert tree.n_leaves == ref_leaf_count(mask)
    pts = center + radius * rng.uniform(-1, 1, size=(4000, 3))
    # plus the centres of all occupied cells (exercises the finest leaves for sparse masks)
    occ = np.argwhere(mask)
    pts = np.concatenate([pts, center - radius + (occ + 0.5) / res * 2 * radius])
    idx = cell_of(pts, center, radius, res)
    expect = np.where(mask[idx[:, 0], idx[:, 1], idx[:, 2]][:, None],
                      values[idx[:, 0], idx[:, 1], idx[:, 2]], 0.0)
    np.testing.assert_array_equal(tree.query(pts), expect)


def test_from_grid_sparse_values_equal_dense():
    rng = np.random.default_rng(7)
    values, mask = random_grid(rng, 16, 0.05, dim=3 * 4 + 1)
    a = Octree.from_grid(values, mask, 0.0, 1.5, "SH4")
    b = Octree.from_grid(values[mask], mask, 0.0, 1.5, "SH4")
    b.check_integrity()
    np.testing.assert_array_equal(a.child, b.child)
    np.testing.assert_array_equal(a.data, b.data)
    assert a.sh_degree == 1 and a.basis_dim == 4 and a.data_dim == 13


def test_leaf_geometry_consistent():
    rng = np.random.default_rng(3)
    values, mask = random_grid(rng, 16, 0.03)
    center, radius = np.array([1.0, 2.0, 3.0]), np.array([0.5, 1.0, 2.0])
    tree = Octree.from_grid(values, mask, center, radius, "RGBA")
    node, i, j, k = tree.leaf_indices()
    centers, sizes, depths = tree.leaf_centers(), tree.leaf_sizes(), tree.leaf_depths()
    assert centers.shape == sizes.shape == (tree.n_leaves, 3) and depths.shape == (tree.n_leaves,)
    np.testing.assert_allclose(sizes, 2 * radius / 2.0 ** (depths[:, None] + 1))
    # leaves tile the box exactly
    np.testing.assert_allclose(np.prod(sizes, -1).sum(), np.prod(2 * radius))
    # each leaf centre is found in that same leaf
    qn, qi, qj, qk, inside = tree.query_cells(centers)
    assert inside.all()
    np.testing.assert_array_equal(np.stack([qn, qi, qj, qk]), np.stack([node, i, j, k]))
    # the deepest occupied leaves sit exactly at the occupied grid cells
    deep = tree.leaf_depths() == tree.depth_limit
    data = tree.leaf_data()
    occ_centres = center - radius + (np.argwhere(mask) + 0.5) / 16 * 2 * radius
    occupied_leaf = deep & (np.abs(data).sum(-1) > 0)
    got = {tuple(np.round(c, 9)) for c in centers[occupied_leaf]}
    assert got == {tuple(np.round(c, 9)) for c in occ_centres}
    np.testing.assert_array_equal(tree.leaf_data(), tree.data[node, i, j, k])


def test_empty_and_full_masks():
    empty = Octree.from_grid(np.ones((8, 8, 8, 4)), np.zeros((8, 8, 8), bool), 0, 1, "RGBA")
    empty.check_integrity()
    assert empty.n_nodes == 1 and empty.n_leaves == 8 and not empty.data.any()
    assert (empty.leaf_depths() == 0).all()
    full = Octree.from_grid(np.ones((8, 8, 8, 4)), np.ones((8, 8, 8), bool), 0, 1, "RGBA")
    full.check_integrity()
    assert full.n_nodes == 1 + 8 + 64 and full.n_leaves == 512 and full.max_depth == 2


def test_breadth_first_order_and_offsets():
    rng = np.random.default_rng(11)
    _, mask = random_grid(rng, 32, 0.01)
    tree = Octree.from_grid(np.ones((32, 32, 32, 4), np.float32), mask, 0, 1, "RGBA")
    depths = tree.node_depths()
    assert (np.diff(depths) >= 0).all()           # breadth-first: depth never decreases
    assert (tree.child >= 0).all()
    assert ref_valid(tree.child, tree.depth_limit)


def test_dense_tree():
    t0 = Octree.dense(0, "SH1")
    assert t0.n_nodes == 1 and t0.n_leaves == 8 and t0.depth_limit == 0
    t = Octree.dense(2, "SG5", center=[1, 0, 0], radius=2.0, seed=1)
    t.check_integrity()
    assert t.n_leaves == 512 and t.extra_data.shape == (5, 4) and t.sh_degree is None
    assert (t.leaf_data()[:, -1] > 0).all()
    assert np.allclose(np.linalg.norm(t.extra_data[:, 1:], axis=-1), 1)
    rgba = dense_tree(1, "RGBA", seed=0)
    assert rgba.basis_dim == 1 and rgba.data_dim == 4


@pytest.mark.parametrize("kwargs,match", [
    (dict(values=np.zeros((6, 6, 6, 4)), mask=np.ones((6, 6, 6), bool)), "power of two"),
    (dict(values=np.zeros((1, 1, 1, 4)), mask=np.ones((1, 1, 1), bool)), "power of two"),
    (dict(values=np.zeros((4, 4, 4, 4)), mask=np.ones((4, 4, 4))), "bool"),
    (dict(values=np.zeros((4, 4, 2, 4)), mask=np.ones((4, 4, 2), bool)), "cube"),
    (dict(values=np.zeros((8, 8, 8, 4)), mask=np.ones((4, 4, 4), bool)), "must match"),
    (dict(values=np.zeros((3, 4)), mask=np.ones((4, 4, 4), bool)), "M = mask.sum"),
    (dict(values=np.zeros((4, 4, 4, 5)), mask=np.ones((4, 4, 4), bool)), "needs 4"),
    (dict(values=-np.ones((4, 4, 4, 4)), mask=np.ones((4, 4, 4), bool)), "sigma"),
    (dict(values=np.full((4, 4, 4, 4), np.nan), mask=np.ones((4, 4, 4), bool)), "finite"),
    (dict(values=np.zeros((4, 4, 4, 4)), mask=np.ones((4, 4, 4), bool), radius=0.0), "radius"),
    (dict(values=np.zeros((4, 4, 4, 4)), mask=np.ones((4, 4, 4), bool), data_format="XYZ"),
     "data_format"),
    (dict(values=np.zeros((4, 4, 4, 7)), mask=np.ones((4, 4, 4), bool), data_format="SG2"),
     "extra_data"),
])
def test_from_grid_rejects_bad_input(kwargs, match):
    kwargs.setdefault("data_format", "RGBA")
    with pytest.raises(ValueError, match=match):
        tree_from_grid(**kwargs)


def test_nan_in_empty_cells_is_ignored():
    values = np.full((4, 4, 4, 4), np.nan, np.float32)
    mask = np.zeros((4, 4, 4), bool)
    mask[1, 2, 3] = True
    values[1, 2, 3] = [1, 2, 3, 4]
    tree = Octree.from_grid(values, mask, 0, 1, "RGBA")
    tree.check_integrity()
    assert tree.query(np.array([-0.25, 0.25, 0.75])).tolist() == [1, 2, 3, 4]


# ---------------------------------------------------------------------- coordinates, query
def test_coordinates_roundtrip_and_box():
    tree = Octree.dense(1, "RGBA", center=[1.0, -2.0, 0.5], radius=[0.5, 1.0, 2.0])
    np.testing.assert_allclose(tree.center, [1.0, -2.0, 0.5])
    np.testing.assert_allclose(tree.radius, [0.5, 1.0, 2.0])
    np.testing.assert_allclose(tree.world_to_tree(tree.bbox), [[0, 0, 0], [1, 1, 1]], atol=1e-12)
    x = np.random.default_rng(0).normal(size=(5, 7, 3))
    np.testing.assert_allclose(tree.tree_to_world(tree.world_to_tree(x)), x, atol=1e-12)


def test_query_outside_boundaries_and_shapes():
    tree = Octree.dense(1, "RGBA", seed=3)
    inside = np.array([[1.0, 1.0, 1.0], [-1.0, -1.0, -1.0], [0.0, 0.0, 0.0]])
    outside = np.array([[1.0001, 0, 0], [0, -1.5, 0], [0, 0, 7.0], [np.nan, 0, 0]])
    q = tree.query(np.concatenate([inside, outside]))
    assert (np.abs(q[:3]).sum(-1) > 0).all() and not q[3:].any()
    # far faces belong to the last cell
    np.testing.assert_array_equal(q[0], tree.data[tree.query_cells(np.full(3, 0.99))[0],
                                                  1, 1, 1])
    pts = np.zeros((2, 3, 5, 3))
    assert tree.query(pts).shape == (2, 3, 5, 4)
    assert tree.query(np.zeros(3)).shape == (4,)
    with pytest.raises(ValueError, match=r"\[\.\.\., 3\]"):
        tree.query(np.zeros((4, 2)))


def test_query_on_cyclic_tree_raises_instead_of_hanging():
    tree = Octree.dense(1, "RGBA")
    tree.child[1, 0, 0, 0] = -1                       # node 1 -> root -> node 1 -> ...
    with pytest.raises(TreeFormatError):
        tree.check_integrity()
    with pytest.raises(TreeFormatError, match="deeper than"):
        tree.query(np.array([-1.0, -1.0, -1.0]))  # stays in cell 0


def test_leaf_data_setter_copy_astype():
    tree = Octree.dense(1, "SH1", seed=0)
    vals = np.random.default_rng(1).random((tree.n_leaves, 4)).astype(np.float32)
    twin = tree.copy()
    tree.set_leaf_data(vals)
    np.testing.assert_array_equal(tree.leaf_data(), vals)
    assert not np.array_equal(twin.leaf_data(), vals)          # copy is independent
    with pytest.raises(ValueError, match="expected shape"):
        tree.set_leaf_data(vals[:-1])
    half = tree.astype(np.float16)
    assert half.data.dtype == np.float16 and tree.data.dtype == np.float32
    assert half.nbytes < tree.nbytes
    half.check_integrity()
    assert "n_leaves=64" in repr(tree)


def test_parse_data_format():
    assert parse_data_format("SH16") == ("SH", 16)
    assert parse_data_format("SG25") == ("SG", 25)
    assert parse_data_format("RGBA") == ("RGBA", 1)
    for bad in ("SH5", "SH", "ASG4", "rgba", "SG0", 3):
        with pytest.raises(TreeFormatError):
            parse_data_format(bad)


# ---------------------------------------------------------------------- check_integrity
def _small():
    mask = np.zeros((8, 8, 8), bool)
    mask[0, 0, 0] = mask[7, 7, 7] = mask[4, 0, 0] = True
    return Octree.from_grid(np.ones((8, 8, 8, 4), np.float32), mask, 0, 1, "RGBA")


def _mutate(what):
    t = _small()
    nz = np.argwhere(t.child > 0)
    if what == "negative":
        t.child[tuple(nz[-1])] = -1
    elif what == "out_of_range":
        t.child[tuple(nz[-1])] = t.n_nodes
    elif what == "shared":
        t.child[tuple(nz[1])] = t.child[tuple(nz[0])] + (nz[0][0] - nz[1][0])
    elif what == "orphan":
        t.child[tuple(nz[-1])] = 0
    elif what == "depth":
        t.depth_limit = 1
    elif what == "nan":
        t.data[3, 0, 1, 0, 2] = np.nan
    elif what == "sigma":
        t.data[0, 0, 0, 0, -1] = -0.5
    elif what == "invradius":
        t.invradius = np.array([0.5, 0.0, 0.5])
    elif what == "data_dim":
        t.data_format = "SH4"
    elif what == "sg_extra":
        t.data_format = "SG1"
    elif what == "child_dtype":
        t.child = t.child.astype(np.int64)
    elif what == "child_shape":
        t.child = t.child.reshape(-1, 2, 4)
    elif what == "data_shape":
        t.data = t.data[:-1]
    elif what == "offset_shape":
        t.offset = np.zeros(2)
    elif what == "no_nodes":
        t.child, t.data = t.child[:0], t.data[:0]
    return t


@pytest.mark.parametrize("what,match", [
    ("negative", "negative"), ("out_of_range", "past the last node"), ("shared", "parents"),
    ("orphan", "no parent"), ("depth", "depth_limit"), ("nan", "not finite"),
    ("sigma", "sigma"), ("invradius", "invradius"), ("data_dim", "data_dim"),
    ("sg_extra", "data_dim|extra_data"), ("child_dtype", "int32"), ("child_shape", "shape"),
    ("data_shape", "shape"), ("offset_shape", "offset"), ("no_nodes", "no nodes"),
])
def test_check_integrity_errors(what, match):
    t = _mutate(what)
    with pytest.raises(TreeFormatError, match=match) as e:
        t.check_integrity("mytree")
    assert str(e.value).startswith("mytree: ")


def test_check_integrity_sg_extra_shape():
    t = Octree.dense(1, "SG2", seed=0)
    t.check_integrity()
    t.extra_data = t.extra_data[:1]
    with pytest.raises(TreeFormatError, match=r"extra_data of shape \[2, 4\]"):
        t.check_integrity()
    t.extra_data = None
    with pytest.raises(TreeFormatError, match="extra_data"):
        t.check_integrity()


@settings(max_examples=150, deadline=None)
@given(st.data())
def test_random_child_mutations_match_reference(data):
    tree = _small()
    n_edits = data.draw(st.integers(1, 4))
    for _ in range(n_edits):
        idx = tuple(data.draw(st.integers(0, s - 1)) for s in tree.child.shape)
        tree.child[idx] = data.draw(st.integers(-3, tree.n_nodes + 2))
    expect = ref_valid(tree.child, tree.depth_limit)
    try:
        tree.check_integrity()
        ok = True
    except TreeFormatError:
        ok = False
    assert ok == expect
    if ok:      # still a tree: query must work and stay inside the arrays
        tree.query(np.random.default_rng(0).uniform(-1, 1, (64, 3)))
