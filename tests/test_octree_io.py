"""Tree files: native save/load, svox export/import, and every kind of bad file."""

from __future__ import annotations

import io
import json
import zipfile

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import plenoctree
from plenoctree import Octree, TreeFormatError, export_svox, import_svox, load_tree, save_tree

SVOX_KEYS = {"child", "data", "data_dim", "data_format", "invradius3", "offset", "parent_depth",
             "n_internal", "n_free", "depth_limit", "geom_resize_fact"}


def sample_tree(fmt="SH4", seed=0):
    rng = np.random.default_rng(seed)
    res = 8
    dim = 4 if fmt == "RGBA" else 3 * int(fmt[2:]) + 1
    mask = rng.random((res, res, res)) < 0.08
    values = rng.normal(size=(res, res, res, dim)).astype(np.float32)
    values[..., -1] = np.abs(values[..., -1]) * 10
    extra = None
    if fmt.startswith("SG"):
        b = int(fmt[2:])
        mu = rng.normal(size=(b, 3))
        extra = np.concatenate([rng.uniform(1, 5, (b, 1)), mu / np.linalg.norm(mu, axis=1,
                                                                                keepdims=True)], 1)
    return Octree.from_grid(values, mask, [0.1, 0.2, -0.3], [1.5, 1.0, 2.0], fmt, extra)


def assert_same_tree(a, b, atol=0.0):
    np.testing.assert_array_equal(a.child, b.child)
    np.testing.assert_allclose(b.data, a.data, atol=atol, rtol=atol)
    np.testing.assert_allclose(b.offset, a.offset, rtol=1e-6)
    np.testing.assert_allclose(b.invradius, a.invradius, rtol=1e-6)
    assert a.data_format == b.data_format and a.depth_limit == b.depth_limit
    if a.extra_data is None:
        assert b.extra_data is None
    else:
        np.testing.assert_allclose(b.extra_data, a.extra_data, rtol=1e-6)


def npz_arrays(path):
    with np.load(path, allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


def write_npz(path, arrays):
    np.savez(path, **arrays)
    return path


# ---------------------------------------------------------------------- native round trips
@pytest.mark.parametrize("fmt", ["SH1", "SH16", "SG3", "RGBA"])
def test_native_roundtrip_fp32_exact(tmp_path, fmt):
    tree = sample_tree(fmt)
    path = tmp_path / "t.npz"
    save_tree(tree, path, precision="fp32")
    back = load_tree(path)
    back.check_integrity()
    assert back.data.dtype == np.float32
    assert_same_tree(tree, back)
    np.testing.assert_array_equal(back.offset, tree.offset)        # float64 kept exactly
    assert [p.name for p in tmp_path.iterdir()] == ["t.npz"]        # no temp file left


def test_native_fp16_and_header(tmp_path):
    tree = sample_tree("SH9")
    path = tmp_path / "half.tree"                                     # any suffix is kept
    save_tree(tree, path, precision="fp16", compressed=True)
    back = load_tree(path)
    assert back.data.dtype == np.float32
    np.testing.assert_allclose(back.data, tree.data, rtol=1e-3, atol=1e-3)
    assert load_tree(path, keep_dtype=True).data.dtype == np.float16
    raw = npz_arrays(path)
    assert int(raw["format_version"]) == 2 and raw["data"].dtype == np.float16
    header = json.loads(str(raw["header"]))
    assert header["data_format"] == "SH9" and header["sh_degree"] == 2
    assert header["dtype"] == "float16" and header["data_dim"] == 28
    assert header["n_nodes"] == tree.n_nodes and header["n_leaves"] == tree.n_leaves
    assert header["package_version"] == plenoctree.__version__
    assert header["ndc"] is None                                    # a world-space tree
    np.testing.assert_allclose(header["bbox"], tree.bbox)


def test_save_refuses_bad_input(tmp_path):
    tree = sample_tree("RGBA")
    with pytest.raises(ValueError, match="precision"):
        save_tree(tree, tmp_path / "a.npz", precision="bf16")
    big = tree.copy()
    big.data[0, 0, 0, 0, -1] = 1e6
    with pytest.raises(ValueError, match="float16 range"):
        save_tree(big, tmp_path / "b.npz", precision="fp16")
    save_tree(big, tmp_path / "b.npz", precision="fp32")              # fine in fp32
    with pytest.raises(ValueError, match="float16 range"):
        export_svox(big, tmp_path / "c.npz")
    bad = tree.copy()
    bad.child[0, 0, 0, 0] = -2
    with pytest.raises(TreeFormatError, match="negative"):
        save_tree(bad, tmp_path / "d.npz")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["b.npz"]


# ---------------------------------------------------------------------- svox
@pytest.mark.parametrize("fmt", ["SH16", "SG2", "RGBA"])
def test_svox_export_import_roundtrip(tmp_path, fmt):
    tree = sample_tree(fmt)
    path = tmp_path / "svox.npz"
    export_svox(tree, path)
    raw = npz_arrays(path)
    assert set(raw) == SVOX_KEYS | ({"extra_data"} if fmt.startswith("SG") else set())
    assert raw["data"].dtype == np.float16 and raw["child"].dtype == np.int32
    assert raw["invradius3"].dtype == np.float32 and raw["offset"].dtype == np.float32
    assert raw["parent_depth"].dtype == np.int32 and raw["parent_depth"].shape == (tree.n_nodes, 2)
    assert str(raw["data_format"]) == fmt and int(raw["data_dim"]) == tree.data_dim
    assert int(raw["n_internal"]) == tree.n_nodes and int(raw["n_free"]) == 0
    # parent_depth: packed parent cell node*8 + i*4 + j*2 + k, and node depth
    pd = raw["parent_depth"]
    for node, i, j, k in np.argwhere(tree.child > 0):
        kid = node + tree.child[node, i, j, k]
        assert pd[kid, 0] == node * 8 + i * 4 + j * 2 + k
        assert pd[kid, 1] == pd[node, 1] + 1
    assert pd[0].tolist() == [-1, 0]
    for back in (import_svox(path), load_tree(path)):
        assert_same_tree(tree, back, atol=2e-3)
        assert back.data.dtype == np.float32


def _hand_written_svox(path, **over):
    """An svox-style file as N3Tree.save writes it: capacity 6 > n_internal 3, float16 data."""
    child = np.zeros((6, 2, 2, 2), np.int32)
    child[0, 1, 0, 0] = 1           # node 1 in root cell (1, 0, 0)
    child[1, 0, 1, 1] = 1           # node 2 in node 1's cell (0, 1, 1)
    child[3:] = 99                  # garbage beyond n_internal must be ignored
    data = np.zeros((6, 2, 2, 2, 13), np.float16)
    data[0, 0, 0, 0] = 1.0
    data[2, 1, 1, 1] = np.arange(13)
    data[3:] = np.nan
    parent_depth = np.zeros((6, 2), np.int32)
    parent_depth[:3] = [[-1, 0], [4, 1], [8 + 3, 2]]
    arrays = dict(child=child, data=data, data_dim=np.int64(13), parent_depth=parent_depth,
                  n_internal=np.int64(3), n_free=np.int64(0), invradius=np.float32(0.25),
                  offset=np.array([0.5, 0.5, 0.5], np.float32), depth_limit=np.int64(8),
                  geom_resize_fact=np.float64(1.5))
    arrays.update(over)
    arrays = {k: v for k, v in arrays.items() if v is not None}
    return write_npz(path, arrays)


def test_hand_written_svox_file(tmp_path):
    path = _hand_written_svox(tmp_path / "legacy.npz")
    for tree in (import_svox(path), load_tree(path)):
        tree.check_integrity()
        assert tree.n_nodes == 3 and tree.data_format == "SH4" and tree.depth_limit == 8
        np.testing.assert_allclose(tree.radius, [2, 2, 2])
        np.testing.assert_allclose(tree.center, [0, 0, 0])
        # node 2 spans tree [0.5, 0.75] x [0.25, 0.5] x [0.25, 0.5]; its cell (1,1,1) is the
        # upper octant, centre tree (0.6875, 0.4375, 0.4375) -> world (0.75, -0.25, -0.25)
        np.testing.assert_array_equal(tree.query(np.array([0.75, -0.25, -0.25])), np.arange(13))
        np.testing.assert_array_equal(tree.query(np.array([-1.0, -1.0, -1.0]))[0], 1.0)
        assert tree.leaf_depths().max() == 2


def test_svox_freed_and_backward_nodes_are_renumbered(tmp_path):
    # node 1 is freed (unreachable, n_free = 1); root -> node 3 -> node 2 (backward offset)
    child = np.zeros((4, 2, 2, 2), np.int32)
    child[0, 0, 0, 0] = 3
    child[3, 1, 1, 1] = -1
    data = np.zeros((4, 2, 2, 2, 4), np.float16)
    data[2, 0, 0, 0] = [1, 2, 3, 4]
    data[1] = -5
    data[3, 0, 0, 0, -1] = -2.0             # negative σ: svox renders it as empty, clamped
    path = write_npz(tmp_path / "f.npz", dict(child=child, data=data, data_format=np.array("RGBA"),
                                              invradius3=np.full(3, 0.5, np.float32),
                                              offset=np.full(3, 0.5, np.float32),
                                              n_internal=np.int64(4), n_free=np.int64(1)))
    tree = import_svox(path)
    assert tree.n_nodes == 3 and (tree.child >= 0).all()
    assert tree.data[..., -1].min() == 0
    # root cell 0 -> node (old 3), its cell (1,1,1) -> node (old 2) whose cell (0,0,0) = data
    np.testing.assert_array_equal(tree.query(np.array([-0.4] * 3)), [1, 2, 3, 4])
    write_npz(path, dict(npz_arrays(path), n_free=np.int64(0)))
    with pytest.raises(TreeFormatError, match="not reachable"):
        import_svox(path)


# ---------------------------------------------------------------------- bad files
def _native_arrays(tmp_path):
    p = tmp_path / "ok.npz"
    save_tree(sample_tree("SH4"), p, precision="fp32")
    return npz_arrays(p)


def _set(arrays, **kw):
    out = dict(arrays)
    for k, v in kw.items():
        if v is None:
            out.pop(k)
        else:
            out[k] = v
    return out


def native_cases(a):
    child = a["child"]
    nz = tuple(np.argwhere(child > 0)[-1])
    neg, oor = child.copy(), child.copy()
    neg[nz] = -1
    oor[nz] = 10 ** 6
    nan = a["data"].copy()
    nan[0, 0, 0, 0, 0] = np.inf
    hdr = json.loads(str(a["header"]))
    return {
        "missing key": (_set(a, child=None), "missing keys"),
        "format version": (_set(a, format_version=np.int64(3)), "unknown format_version 3"),
        "header ndc": (_set(a, header=np.array(json.dumps({**hdr, "ndc": {"width": 0}}))),
                       "header 'ndc': NDC settings must be an object"),
        "header ndc value": (_set(a, header=np.array(json.dumps(
            {**hdr, "ndc": {"width": 8, "height": 6, "fx": -1, "fy": 5, "near": 1}}))),
            "header 'ndc': NDC fx must be a finite positive number"),
        "version dtype": (_set(a, format_version=np.float32(1)), "integer scalar"),
        "header json": (_set(a, header=np.array("{not json")), "not valid JSON"),
        "header type": (_set(a, header=np.array("[1, 2]")), "JSON object"),
        "header format": (_set(a, header=np.array(json.dumps({**hdr, "data_format": "SH5"}))),
                          "unknown data_format|SH basis"),
        "data_dim": (_set(a, header=np.array(json.dumps({**hdr, "data_format": "SH9"}))),
                     "data_dim 13 does not match"),
        "child dtype": (_set(a, child=child.astype(np.float32)), "int32"),
        "child shape": (_set(a, child=child.reshape(-1, 4, 2)), "shape"),
        "data shape": (_set(a, data=a["data"][:-1]), "shape"),
        "data dtype": (_set(a, data=a["data"].astype(np.int32)), "float16/float32"),
        "offset shape": (_set(a, offset=np.zeros(4)), "offset"),
        "negative": (_set(a, child=neg), "negative"),
        "out of range": (_set(a, child=oor), "past the last node"),
        "non-finite": (_set(a, data=nan), "not finite"),
        "invradius": (_set(a, invradius3=np.array([1.0, -1.0, 1.0])), "invradius"),
        "dtype header": (_set(a, data=a["data"].astype(np.float16)), "header dtype"),
    }


def test_native_bad_files(tmp_path):
    a = _native_arrays(tmp_path)
    for name, (arrays, match) in native_cases(a).items():
        path = write_npz(tmp_path / f"{name.replace(' ', '_')}.npz", arrays)
        with pytest.raises(TreeFormatError, match=match) as e:
            load_tree(path)
        assert str(path) in str(e.value), name


def test_svox_bad_files(tmp_path):
    good = npz_arrays(_hand_written_svox(tmp_path / "g.npz"))
    child = good["child"].copy()
    cyc = child.copy()
    cyc[2, 0, 0, 0] = -2                  # node 2 -> root: cycle
    shared = child.copy()
    shared[0, 0, 0, 0] = 2                # root also points at node 2
    oor = child.copy()
    oor[1, 0, 1, 1] = 5                   # beyond n_internal
    nan = good["data"].copy()
    nan[1, 0, 0, 0, 0] = np.nan
    cases = {
        "missing": (_set(good, offset=None), "missing keys"),
        "no invradius": (_set(good, invradius=None), "invradius"),
        "data_dim": (_set(good, data_dim=np.int64(12)), "data_dim 12 does not match"),
        "infer": (_set(good, data=good["data"][..., :12], data_dim=None), "cannot infer"),
        "format mismatch": (_set(good, data_format=np.array("SH9")), "data_dim 13"),
        "asg": (_set(good, data_format=np.array("ASG4")), "not supported"),
        "n_internal": (_set(good, n_internal=np.int64(9)), "n_internal"),
        "parent_depth": (_set(good, parent_depth=np.zeros((6, 3), np.int32)), "parent_depth"),
        "cycle": (_set(good, child=cyc), "do not form a tree"),
        "shared": (_set(good, child=shared), "do not form a tree"),
        "out of range": (_set(good, child=oor), "outside"),
        "non-finite": (_set(good, data=nan), "not finite"),
        "depth": (_set(good, depth_limit=np.int64(1)), "depth_limit"),
        "sg extra": (_set(good, data_format=np.array("SG4")), "extra_data"),
        "child dtype": (_set(good, child=child.astype(np.float64)), "int"),
    }
    for name, (arrays, match) in cases.items():
        path = write_npz(tmp_path / f"{name.replace(' ', '_')}.npz", arrays)
        with pytest.raises(TreeFormatError, match=match) as e:
            import_svox(path)
        assert str(path) in str(e.value), name


def test_not_a_tree_files(tmp_path):
    text = tmp_path / "text.npz"
    text.write_text("hello")
    npy = tmp_path / "arr.npz"
    with open(npy, "wb") as f:
        np.save(f, np.zeros(3))
    pickled = tmp_path / "pickled.npz"
    a = _native_arrays(tmp_path)
    np.savez(pickled, **_set(a, header=np.array([{"x": 1}], dtype=object)))
    other = write_npz(tmp_path / "other.npz", {"x": np.zeros(3)})
    cases = {text: "not a zip", npy: "not a zip", tmp_path / "missing.npz": "no such file",
             tmp_path: "not a regular file", pickled: "Python objects", other: "not a tree"}
    for path, match in cases.items():
        with pytest.raises(TreeFormatError, match=match) as e:
            load_tree(path)
        assert str(path) in str(e.value)
    native = tmp_path / "native.npz"
    save_tree(sample_tree("RGBA"), native)
    with pytest.raises(TreeFormatError, match="use load_tree"):
        import_svox(native)
    compressed = write_npz(tmp_path / "c.npz", {"quant_colors": np.zeros((3, 4, 3), np.float16),
                                                 "child": np.zeros((1, 2, 2, 2), np.int32)})
    with pytest.raises(TreeFormatError, match="compressed svox"):
        load_tree(compressed)


def test_truncated_member_and_lying_header(tmp_path):
    path = tmp_path / "t.npz"
    save_tree(sample_tree("SH1"), path)
    # rewrite 'data' with a header claiming a huge array but only a few bytes of payload
    buf = io.BytesIO()
    np.lib.format.write_array_header_1_0(buf, {"descr": "<f4", "fortran_order": False,
                                               "shape": (10 ** 6, 2, 2, 2, 4)})
    buf.write(b"\0" * 64)
    with zipfile.ZipFile(path) as z:
        members = {n: z.read(n) for n in z.namelist()}
    members["data.npy"] = buf.getvalue()
    with zipfile.ZipFile(path, "w") as z:
        for n, b in members.items():
            z.writestr(n, b)
    with pytest.raises(TreeFormatError, match="truncated or corrupt"):
        load_tree(path)


# ---------------------------------------------------------------------- fuzzing
def _valid_bytes(kind: str) -> bytes:
    buf = io.BytesIO()
    tree = Octree.dense(1, "SH1", seed=0)
    if kind == "native":
        np.savez(buf, format_version=np.int64(1),
                 header=np.array(json.dumps({"data_format": "SH1", "depth_limit": 1})),
                 child=tree.child, data=tree.data, offset=tree.offset, invradius3=tree.invradius)
    else:
        np.savez(buf, child=tree.child, data=tree.data.astype(np.float16), data_dim=np.int64(4),
                 offset=tree.offset.astype(np.float32),
                 invradius3=tree.invradius.astype(np.float32),
                 n_internal=np.int64(tree.n_nodes))
    return buf.getvalue()


VALID = {k: _valid_bytes(k) for k in ("native", "svox")}
FUZZ = settings(max_examples=60, deadline=None,
                suppress_health_check=[HealthCheck.function_scoped_fixture])


def _load_or_format_error(path, loader):
    try:
        tree = loader(path)
    except TreeFormatError as e:
        assert str(path) in str(e)
        return
    assert isinstance(tree, Octree)
    tree.check_integrity()          # anything returned is a complete, valid tree


@pytest.mark.parametrize("loader", [load_tree, import_svox])
def test_valid_fuzz_seeds_load(tmp_path, loader):
    for kind, blob in VALID.items():
        p = tmp_path / f"{kind}.npz"
        p.write_bytes(blob)
        if loader is import_svox and kind == "native":
            continue
        assert loader(p).n_nodes == 9


@FUZZ
@given(blob=st.binary(max_size=2000))
def test_random_bytes(tmp_path, blob):
    path = tmp_path / "r.npz"
    path.write_bytes(blob)
    for loader in (load_tree, import_svox):
        with pytest.raises(TreeFormatError):
            loader(path)


@FUZZ
@given(kind=st.sampled_from(["native", "svox"]), frac=st.floats(0.0, 0.999))
def test_truncated_files(tmp_path, kind, frac):
    blob = VALID[kind]
    path = tmp_path / "t.npz"
    path.write_bytes(blob[:int(len(blob) * frac)])
    for loader in (load_tree, import_svox):
        with pytest.raises(TreeFormatError):
            loader(path)


@FUZZ
@given(kind=st.sampled_from(["native", "svox"]), edits=st.lists(
    st.tuples(st.floats(0, 0.999), st.integers(0, 255)), min_size=1, max_size=8))
def test_corrupted_bytes(tmp_path, kind, edits):
    blob = bytearray(VALID[kind])
    for where, value in edits:
        blob[int(where * len(blob))] = value
    path = tmp_path / "c.npz"
    path.write_bytes(bytes(blob))
    for loader in (load_tree, import_svox):
        _load_or_format_error(path, loader)


@FUZZ
@given(kind=st.sampled_from(["native", "svox"]), data=st.data())
def test_mutated_arrays(tmp_path, kind, data):
    with np.load(io.BytesIO(VALID[kind]), allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    key = data.draw(st.sampled_from(sorted(arrays)))
    a = arrays[key]
    op = data.draw(st.sampled_from(["value", "shape", "dtype", "drop"]))
    if op == "value" and a.size and a.dtype.kind in "iuf":
        a = a.copy()
        flat = a.reshape(-1)
        with np.errstate(over="ignore", invalid="ignore"):
            flat[data.draw(st.integers(0, a.size - 1))] = data.draw(st.sampled_from(
                [-1, 0, 1, 5, 8, 9, 1000, -(2 ** 31), np.nan, np.inf]) if a.dtype.kind == "f"
                else st.integers(-20, 20))
    elif op == "shape" and a.size > 1:
        a = a.reshape(-1)[:data.draw(st.integers(0, a.size - 1))]
    elif op == "dtype":
        dtype = data.draw(st.sampled_from([np.int64, np.float64, np.uint8, np.bool_, np.bytes_]))
        a = np.zeros(a.shape, dtype) if a.dtype.kind == "U" else a.astype(dtype)
    elif op == "drop":
        a = None
    path = write_npz(tmp_path / "m.npz", _set(arrays, **{key: a}))
    for loader in (load_tree, import_svox):
        _load_or_format_error(path, loader)


def test_stored_members_read_directly_and_crc_checked(tmp_path):
    """Uncompressed members are read straight from the archive (no zipfile copies); a flipped
    byte in an array is caught by the member's CRC-32, and DEFLATE members load as before."""
    good = tmp_path / "g.npz"
    good.write_bytes(VALID["native"])
    ref = load_tree(good)
    with np.load(good, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    packed = tmp_path / "deflate.npz"
    np.savez_compressed(packed, **arrays)
    back = load_tree(packed)
    np.testing.assert_array_equal(back.child, ref.child)
    np.testing.assert_array_equal(back.data, ref.data)
    with zipfile.ZipFile(good) as z:
        info = z.getinfo("data.npy")
    assert info.compress_type == zipfile.ZIP_STORED
    blob = bytearray(VALID["native"])
    local = blob[info.header_offset:info.header_offset + 30]
    start = (info.header_offset + 30 + int.from_bytes(local[26:28], "little")
             + int.from_bytes(local[28:30], "little"))
    blob[start + info.file_size - 1] ^= 0x01      # last byte of the array payload
    bad = tmp_path / "b.npz"
    bad.write_bytes(bytes(blob))
    with pytest.raises(TreeFormatError, match="CRC-32"):
        load_tree(bad)


def test_big_endian_and_fortran_members_load(tmp_path):
    """Fortran-ordered members load C-contiguous; a big-endian array comes back native."""
    from plenoctree._npz import NpzReader

    tree = Octree.dense(1, "SH1", seed=0)
    path = tmp_path / "f.npz"
    np.savez(path, format_version=np.int64(1),
             header=np.array(json.dumps({"data_format": "SH1", "depth_limit": 1})),
             child=tree.child, data=np.asfortranarray(tree.data),
             offset=tree.offset, invradius3=tree.invradius)
    back = load_tree(path)
    assert back.data.flags.c_contiguous
    np.testing.assert_array_equal(back.data, tree.data)
    be = tmp_path / "be.npz"
    np.savez(be, x=np.arange(12, dtype=">f8").reshape(3, 4))
    with NpzReader(be) as r:
        x = r.read("x")
    assert x.dtype.isnative
    np.testing.assert_array_equal(x, np.arange(12.0).reshape(3, 4))
