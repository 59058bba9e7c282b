"""The compressed tree file (``.plnz``): a DEFLATE zip of ``.npy`` arrays, readable by ``np.load``.

=================  ==================================  =========================================
key                dtype / shape                       meaning
=================  ==================================  =========================================
``plnz_version``   int64 scalar                        2 (version 1 files, without
                                                       ``ndc``, still load)
``header``         unicode scalar (JSON)               ``format: "plenoctree-compressed"``,
                                                       data_format, basis_dim, bits, retain,
                                                       sigma_thresh, n_nodes, n_kept, bbox,
                                                       depth_limit, package_version, ``ndc``
                                                       (null or the NDCSpace JSON, v2)
``child``          int32 ``[n, 2, 2, 2]``              relative child offsets, 0 = leaf
``offset``         float64 ``[3]``                     tree = offset + invradius3 * world
``invradius3``     float64 ``[3]``                     0.5 / radius
``data_dim``       int64 scalar                        3 B + 1 (svox key)
``data_format``    unicode scalar                      svox key
``depth_limit``    int64 scalar
``sigma``          float16 ``[n, 2, 2, 2]``            σ of kept leaves, else 0
``quant_colors``   float16 ``[B - r, 2**bits, 3]``     one RGB codebook per quantised basis
``quant_map``      uint16 ``[B - r, n, 2, 2, 2]``      codebook index per cell
``data_retained``  float16 ``[r, n, 2, 2, 2, 3]``      only when ``retain = r > 0``
``extra_data``     float32 ``[B, 4]``                  SG lobes only
``ndc_config``     float64 ``[5]``                     NDC trees only: width, height, fx, fy,
                                                       near (as in the svox layout)
=================  ==================================  =========================================

The keys ``sigma``, ``quant_colors``, ``quant_map``, ``data_retained``, ``child``, ``offset``,
``invradius3``, ``data_dim`` and ``data_format`` are those of the original PlenOctree /
volrend compressed files; :func:`load_compressed` also reads those files (no header; capacity
rows past the last reachable node are dropped). The web viewer reads the same file in the
browser.
"""

from __future__ import annotations

import json
import math
import os
import zipfile
from pathlib import Path

import numpy as np

from .._util import atomic_write
from ..errors import TreeFormatError
from ..octree import Octree
from .._npz import NpzReader
from ..octree.limits import MAX_DEPTH
from ..octree.ndc import NDCSpace
from .codec import CompressedTree, CompressOptions, decompress

__all__ = ["PLNZ_VERSION", "save_compressed", "load_compressed", "is_compressed_file",
           "load_any_tree"]

PLNZ_VERSION = 2
READ_VERSIONS = (1, 2)       # 1: no "ndc" in the header
_ZIP64_LIMIT = (1 << 31) - (1 << 20)


def _arrays(ctree: CompressedTree) -> dict[str, np.ndarray]:
    from .. import __version__

    opts = ctree.options
    b = ctree.basis_dim
    bbox = np.stack([(0.0 - ctree.offset) / ctree.invradius, (1.0 - ctree.offset) / ctree.invradius])
    header = {
        "format": "plenoctree-compressed",
        "data_format": ctree.data_format,
        "basis_dim": b,
        "bits": int(round(math.log2(max(ctree.quant_colors.shape[1], 1)))),
        "retain": int(ctree.data_retained.shape[0]),
        "sigma_thresh": float(opts.sigma_thresh),
        "n_nodes": ctree.n_nodes,
        "n_kept": ctree.n_kept,
        "bbox": bbox.tolist(),
        "depth_limit": int(ctree.depth_limit),
        "package_version": __version__,
        "ndc": None if ctree.ndc is None else ctree.ndc.to_json(),
    }
    arrays = {
        "plnz_version": np.int64(PLNZ_VERSION),
        "header": np.array(json.dumps(header)),
        "child": ctree.child.astype(np.int32),
        "offset": ctree.offset.astype(np.float64),
        "invradius3": ctree.invradius.astype(np.float64),
        "data_dim": np.int64(4 if ctree.data_format == "RGBA" else 3 * b + 1),
        "data_format": np.array(ctree.data_format),
        "depth_limit": np.int64(ctree.depth_limit),
        "sigma": ctree.sigma.astype(np.float16),
        "quant_colors": ctree.quant_colors.astype(np.float16),
        "quant_map": ctree.quant_map.astype(np.uint16),
    }
    if ctree.data_retained.shape[0]:
        arrays["data_retained"] = ctree.data_retained.astype(np.float16)
    if ctree.extra_data is not None:
        arrays["extra_data"] = ctree.extra_data.astype(np.float32)
    if ctree.ndc is not None:
        arrays["ndc_config"] = ctree.ndc.as_array()
    return arrays


def save_compressed(ctree: CompressedTree, path: str | os.PathLike,
                    level: int | None = None) -> int:
    """Write ``ctree`` to ``path`` as a ``.plnz`` (DEFLATE zip), atomically.

    Args:
        level: DEFLATE level 0..9 (default: ``ctree.options.level``).
    Returns:
        The file size in bytes.
    """
    ctree.validate(f"save_compressed({os.fspath(path)})")
    lvl = ctree.options.level if level is None else int(level)
    if not 0 <= lvl <= 9:
        raise ValueError(f"save_compressed: level must be in 0..9, got {level!r}")
    with atomic_write(path, "wb") as f:
        with zipfile.ZipFile(f, "w", compression=zipfile.ZIP_DEFLATED, compresslevel=lvl) as zf:
            for key, arr in _arrays(ctree).items():
                arr = np.asanyarray(arr)
                with zf.open(f"{key}.npy", "w", force_zip64=arr.nbytes > _ZIP64_LIMIT) as member:
                    np.lib.format.write_array(member, arr, allow_pickle=False)
    return Path(path).stat().st_size


def is_compressed_file(path: str | os.PathLike) -> bool:
    """True if ``path`` is a zip holding ``quant_colors`` / ``quant_map`` (``.plnz`` or svox)."""
    try:
        with zipfile.ZipFile(path) as zf:
            names = set(zf.namelist())
    except (OSError, zipfile.BadZipFile, ValueError):
        return False
    return "quant_colors.npy" in names or "quant_map.npy" in names


def _read_float(r: NpzReader, key: str, shape: tuple[int, ...]) -> np.ndarray:
    s, dt = r.shape(key), r.dtype(key)
    if dt.kind != "f" or s != shape:
        r.fail(f"{key!r} must be float {list(shape)}, got {dt} {list(s)}")
    return r.read(key)


def _vec3(r: NpzReader, *keys: str) -> np.ndarray:
    for key in keys:
        if key in r:
            s, dt = r.shape(key), r.dtype(key)
            if dt.kind not in "fiu" or s not in ((3,), (), (1,)):
                r.fail(f"{key!r} must be a float array of shape [3], got {dt} {list(s)}")
            v = np.broadcast_to(r.read(key).astype(np.float64).reshape(-1), (3,)).copy()
            if not np.isfinite(v).all():
                r.fail(f"{key!r} has non-finite values {v.tolist()}")
            return v
    r.fail(f"missing key {keys[0]!r} (found {r.keys()})")
    raise AssertionError("unreachable")


def _format_of(r: NpzReader, header: dict, n_bases: int) -> str:
    fmt = header.get("data_format")
    if fmt is None and "data_format" in r:
        fmt = r.scalar_str("data_format")
    if fmt is None:                  # legacy svox file: SH inferred from the basis count
        if n_bases not in (1, 4, 9, 16, 25):
            r.fail(f"no data_format and {n_bases} bases is not an SH basis count")
        fmt = f"SH{n_bases}"
    if not isinstance(fmt, str):
        r.fail(f"data_format must be a string, got {fmt!r}")
    return fmt


# Header keys written by _arrays and the JSON types they must have when present.
_HEADER_TYPES = {"format": str, "data_format": str, "basis_dim": int, "bits": int, "retain": int,
                 "sigma_thresh": (int, float), "n_nodes": int, "n_kept": int, "bbox": list,
                 "depth_limit": int, "package_version": str}


def _check_header(r: NpzReader, header: dict) -> None:
    """Types and ranges of the ``.plnz`` header fields (a bad header is one clear error)."""
    for key, typ in _HEADER_TYPES.items():
        if key in header:
            v = header[key]
            if isinstance(v, bool) or not isinstance(v, typ):
                name = typ.__name__ if isinstance(typ, type) else "number"
                r.fail(f"header {key!r} must be a JSON {name}, got {v!r}")
    if header.get("format", "plenoctree-compressed") != "plenoctree-compressed":
        r.fail(f"header format {header['format']!r} is not 'plenoctree-compressed'")
    thr = header.get("sigma_thresh", 0.0)
    if not (math.isfinite(thr) and thr >= 0):
        r.fail(f"header 'sigma_thresh' must be a finite number >= 0, got {thr!r}")
    for key in ("basis_dim", "bits", "n_nodes", "n_kept", "depth_limit"):
        if header.get(key, 0) < 0:
            r.fail(f"header {key!r} must be >= 0, got {header[key]!r}")
    if "n_nodes" in header and "child" in r and len(r.shape("child")) == 4 \
            and header["n_nodes"] != r.shape("child")[0]:
        r.fail(f"header n_nodes={header['n_nodes']} does not match 'child' "
               f"({r.shape('child')[0]} nodes)")


def _read_ndc(r: NpzReader, header: dict) -> NDCSpace | None:
    """The tree's NDC space: header ``ndc`` (v2), else an ``ndc_config`` array, else None."""
    if header.get("ndc") is None and "ndc_config" not in r:
        return None
    if header.get("ndc") is None:
        s, dt = r.shape("ndc_config"), r.dtype("ndc_config")
        if dt.kind not in "fiu" or s != (5,):
            r.fail(f"'ndc_config' must be 5 numbers (width, height, fx, fy, near), got {dt} "
                   f"{list(s)}")
    try:
        if header.get("ndc") is not None:
            return NDCSpace.from_json(header["ndc"], "header 'ndc'")
        return NDCSpace.from_array(r.read("ndc_config"))
    except TreeFormatError as e:
        r.fail(str(e))
    raise AssertionError("unreachable")


def load_compressed(path: str | os.PathLike) -> CompressedTree:
    """Read a ``.plnz`` file (or an original PlenOctree compressed ``.npz``).

    Raises:
        TreeFormatError: not a zip, truncated, missing or inconsistent arrays, a codebook index
        out of range, an unknown ``plnz_version``: the message names the file and the problem.
    """
    with NpzReader(path) as r:
        if "quant_colors" not in r or "quant_map" not in r or "sigma" not in r:
            hint = " (an uncompressed tree: load it with load_tree)" if "data" in r else ""
            r.fail("not a compressed tree: needs 'quant_colors', 'quant_map' and 'sigma', "
                   f"found {r.keys()}{hint}")
        header: dict = {}
        if "plnz_version" in r:
            version = r.scalar_int("plnz_version")
            if version not in READ_VERSIONS:
                r.fail(f"unknown plnz_version {version} (this plenoctree reads versions "
                       f"{', '.join(map(str, READ_VERSIONS))}; a newer plenoctree may read it)")
            header = r.json("header")
            _check_header(r, header)
        r.require("child")
        cs, cd = r.shape("child"), r.dtype("child")
        if cd.kind not in "iu" or len(cs) != 4 or cs[1:] != (2, 2, 2) or cs[0] < 1:
            r.fail(f"'child' must be int [n_nodes >= 1, 2, 2, 2], got {cd} {list(cs)}")
        n = cs[0]
        cells = (n, 2, 2, 2)
        qcs = r.shape("quant_colors")
        if len(qcs) != 3 or qcs[2] != 3:
            r.fail(f"'quant_colors' must have shape [bases, codebook size, 3], got {list(qcs)}")
        quant_colors = _read_float(r, "quant_colors", qcs)
        qms, qmd = r.shape("quant_map"), r.dtype("quant_map")
        if qmd.kind not in "iu" or qms != (qcs[0],) + cells:
            r.fail(f"'quant_map' must be uint16 {[qcs[0], *cells]}, got {qmd} {list(qms)}")
        sigma = _read_float(r, "sigma", cells)
        if "data_retained" in r:
            rs = r.shape("data_retained")
            if len(rs) != 6 or rs[1:] != cells + (3,):
                r.fail(f"'data_retained' must have shape [retain, {n}, 2, 2, 2, 3], "
                       f"got {list(rs)}")
            retained = _read_float(r, "data_retained", rs)
        else:
            retained = np.zeros((0,) + cells + (3,), dtype=np.float16)
        fmt = _format_of(r, header, qcs[0] + retained.shape[0])
        extra = None
        if fmt.startswith("SG"):
            r.require("extra_data")
            b = qcs[0] + retained.shape[0]
            extra = _read_float(r, "extra_data", (b, 4)).astype(np.float32)
            if not np.isfinite(extra).all():
                r.fail("'extra_data' holds NaN or infinite values")
        depth_limit = r.scalar_int("depth_limit") if "depth_limit" in r else -1
        if not header and depth_limit > MAX_DEPTH:     # svox: only caps future refinement
            depth_limit = MAX_DEPTH
        child = r.read("child")
        if child.dtype != np.int32:
            if child.size and np.abs(child.astype(np.int64)).max() >= n:
                r.fail("child offsets exceed the node count")
            child = child.astype(np.int32)
        quant_map = r.read("quant_map")
        if quant_map.dtype != np.uint16:
            if quant_map.size and (quant_map.min() < 0 or quant_map.max() > 65535):
                r.fail("quant_map values outside 0..65535")
            quant_map = quant_map.astype(np.uint16)
        if not header and n > 1:        # svox file: may hold unused capacity rows
            from ..octree.io import _bfs_order, _renumber
            order = _bfs_order(r, child, allow_orphans=True)
            if order is not None:
                child = _renumber(child, order)
                sigma, quant_map = sigma[order], quant_map[:, order]
                retained = retained[:, order]
        ndc = _read_ndc(r, header)
        bits = header.get("bits", int(round(math.log2(max(qcs[1], 1)))))
        opts = CompressOptions(bits=int(bits) if isinstance(bits, int) and 1 <= bits <= 16 else 16,
                               retain=int(retained.shape[0]),
                               sigma_thresh=float(header.get("sigma_thresh", 0.0)))
        ctree = CompressedTree(child=child, offset=_vec3(r, "offset"),
                               invradius=_vec3(r, "invradius3", "invradius"), data_format=fmt,
                               extra_data=extra, depth_limit=depth_limit,
                               sigma=np.maximum(sigma, 0).astype(np.float16),
                               quant_colors=quant_colors.astype(np.float16),
                               quant_map=quant_map, data_retained=retained.astype(np.float16),
                               options=opts, ndc=ndc)
        ctree.validate(r.name)
        if not (ctree.invradius > 0).all():
            r.fail(f"'invradius3' must be > 0, got {ctree.invradius.tolist()}")
    return ctree


def load_any_tree(path: str | os.PathLike) -> Octree:
    """Load a tree file of any kind this package reads: native, svox, ``.plnz`` or svox
    compressed (decompressed on load). Raises :class:`TreeFormatError` naming the file."""
    if is_compressed_file(path):
        return decompress(load_compressed(path), name=os.fspath(path))
    from ..octree.io import load_tree

    return load_tree(path)
