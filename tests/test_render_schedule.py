"""How the numba renderer shares an image between threads: the balance model of
``benchmarks/_balance.py`` (against numba's real static ``prange`` schedule and on a centred
cost blob), the shared work counter, and an image that does not depend on the schedule."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numba
import numpy as np
import pytest

_BENCH = Path(__file__).resolve().parents[1] / "benchmarks"


@pytest.fixture()
def bal(monkeypatch):
    monkeypatch.syspath_prepend(str(_BENCH))
    import _balance

    return _balance


def _blob(size: int = 800) -> np.ndarray:
    """Segments per ray of a centred object: 40 in a disc of radius size / 4, 0 elsewhere."""
    y, x = np.mgrid[:size, :size] + 0.5 - size / 2
    return np.where(np.hypot(x, y) < size / 4, 40.0, 0.0)


def test_static_chunks_leave_threads_idle_the_counter_keeps_them_busy(bal):
    costs = bal.tile_costs(_blob(), (24, 24))
    assert costs.size == 34 * 34 and costs.sum() == _blob().sum()
    for t in (4, 8, 16, 32):       # (2 threads split a centred blob evenly: 0.95)
        static = bal.balance(bal.per_thread_work(costs, t, "static", chunksize=4))
        dynamic = bal.balance(bal.per_thread_work(costs, t, "dynamic"))
        assert static <= 0.5, (t, static)          # only the threads of the blob's rows work
        assert dynamic >= (0.95 if t <= 16 else 0.9), (t, dynamic)
    assert bal.balance(bal.per_thread_work(costs, 1, "static", chunksize=4)) == 1.0
    w = bal.per_thread_work(costs, 16, "dynamic")
    assert w.sum() == costs.sum() and w.shape == (16,)


def test_dynamic_model_is_list_scheduling(bal):
    w = bal.dynamic_work(np.array([5.0, 1, 1, 1, 1, 1]), 2)
    np.testing.assert_array_equal(w, [5.0, 5.0])         # the 1s go to the free thread
    assert bal.balance(np.zeros(4)) == 1.0
    assert bal.balance(np.array([1.0, 3.0])) == pytest.approx(2 / 3)
    np.testing.assert_array_equal(bal.per_thread_work(np.ones(7), 3, "cyclic"), [3, 2, 2])
    with pytest.raises(ValueError, match="schedule"):
        bal.per_thread_work(np.ones(3), 2, "guided")


_PROBE = """
import json, numba, numpy as np
@numba.njit(parallel=True)
def owner(a):
    for i in numba.prange(a.size):
        a[i] = numba.get_thread_id()
out = {}
for n in (3, 37, 100, 289, 1156):
    for t in (1, 2, 3, 5, 8):
        for c in (0, 1, 4):
            numba.set_num_threads(t)
            old = numba.set_parallel_chunksize(c)
            a = np.full(n, -1, np.int64)
            owner(a)
            numba.set_parallel_chunksize(old)
            out[f"{n} {t} {c}"] = a.tolist()
print(json.dumps({"layer": numba.threading_layer(), "owner": out}))
"""


def test_static_model_is_numbas_schedule(bal):
    """static_owner gives every item to the thread numba's prange really runs it on."""
    res = subprocess.run([sys.executable, "-c", _PROBE], capture_output=True, text=True,
                         env={**os.environ, "NUMBA_NUM_THREADS": "8"}, check=True, timeout=600)
    got = json.loads(res.stdout.strip().splitlines()[-1])
    if got["layer"] not in bal.LAYERS:
        pytest.skip(f"threading layer {got['layer']} schedules dynamically")
    for key, owner in got["owner"].items():
        n, t, c = map(int, key.split())
        np.testing.assert_array_equal(bal.static_owner(n, t, c, got["layer"]), owner,
                                      err_msg=key)


def test_work_counter_hands_out_every_item_once():
    from plenoctree.render._schedule_numba import next_item

    @numba.njit(parallel=True)
    def claim(n, threads, hits, who):
        counter = np.zeros(1, np.int64)
        for _ in numba.prange(max(1, min(threads, n))):
            while True:
                i = next_item(counter)
                if i >= n:
                    break
                hits[i] += 1
                who[i] = numba.get_thread_id()

    for n in (0, 1, 3, 5000):
        hits, who = np.zeros(n, np.int64), np.full(n, -1, np.int64)
        claim(n, numba.get_num_threads(), hits, who)
        assert (hits == 1).all() and (who >= 0).all() and (who < numba.get_num_threads()).all()


def test_image_bits_do_not_depend_on_the_schedule():
    """The same image, bit for bit, on 1 thread and on every thread, in any tile shape."""
    from plenoctree.datasets.procedural import look_at, procedural_tree
    from plenoctree.render import tree_to_device
    from plenoctree.render import _render_numba as kern
    from plenoctree.render.options import RenderOptions, parse_data_format

    tree = procedural_tree(32)
    info = parse_data_format(tree.data_format, tree.data_dim, tree.extra_data)
    spec = kern.prepare(tree_to_device(tree, "cpu"), info, RenderOptions())   # + skip tables
    c2w = look_at(np.array([2.0, -2.5, 1.8]), np.zeros(3))
    cam = kern.pack_camera(c2w, 70.0, 70.0, 30.5, 30.5)   # 61 x 61: not a multiple of the tile

    def render(threads: int, tile=None):
        old = numba.get_num_threads()
        numba.set_num_threads(threads)
        try:
            out = kern.empty_outputs(61 * 61)
            kern.render_camera_prepared(spec, cam, 61, 61, out, tile)
        finally:
            numba.set_num_threads(old)
        return out

    ref = render(1)
    assert ref[2].max() > 0.5                            # the object is in view
    for threads, tile in ((numba.config.NUMBA_NUM_THREADS, None), (1, (5, 3)),
                          (numba.config.NUMBA_NUM_THREADS, (1, 1)),
                          (numba.config.NUMBA_NUM_THREADS, (64, 64))):
        for a, b in zip(render(threads, tile), ref):
            np.testing.assert_array_equal(a, b, err_msg=f"{threads} threads, tile {tile}")
