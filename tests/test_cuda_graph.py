"""The fixed-shape step replayed from a CUDA graph (``cuda_graph``, ``nerf/graph.py``), proven
on the CPU: the graph-ready step trains bit for bit as the plain fixed step; two steps of one
ray count launch the same ops with the same arguments on the same outside tensors (what a
replay repeats); and :class:`StepGraphs` warms up, captures once per ray count, replays,
copies its outputs and keeps at most ``KEEP`` graphs (with CUDA's graph calls stood in for).
The capture itself and its speed need a GPU (``benchmarks/gpu_bench.py``)."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
import torch

from nerf_fixtures import tiny_cpu_config, tiny_dataset

from plenoctree.nerf import graph as G

_BENCH = Path(__file__).resolve().parents[1] / "benchmarks"


@pytest.fixture(scope="module")
def data(tmp_path_factory) -> Path:
    return tiny_dataset(tmp_path_factory.mktemp("graph_data"))


def _trainer(data: Path, out: Path, graph: bool):
    from plenoctree.nerf.trainer import Trainer

    cfg = tiny_cpu_config(data, out, steps=10**6)
    cfg.fixed_step, cfg.cuda_graph, cfg.val_views, cfg.amp = True, graph, 0, "off"
    tr = Trainer(cfg, quiet=True)
    tr.setup()
    return tr


def test_the_graph_ready_step_trains_bit_for_bit_as_the_fixed_step(data, tmp_path):
    from plenoctree._util import progress

    bar, runs = progress(total=1, disable=True), {}
    for graph in (False, True):
        tr = _trainer(data, tmp_path / str(graph), graph)
        for _ in range(24):                  # occupancy updates and ray-count adaptations
            tr.iteration(bar)
        tr.read_losses()
        runs[graph] = (tr, [p.detach().clone() for p in tr.model.parameters()])
    (plain, p0), (ready, p1) = runs[False], runs[True]
    assert ready.graphs is not None and plain.graphs is None
    assert isinstance(ready.opt.param_groups[0]["lr"], torch.Tensor)
    for a, b in zip(p0, p1):
        assert torch.equal(a, b)
    assert plain.state.n_rays == ready.state.n_rays and plain.state.spr == ready.state.spr
    assert plain.state.win.loss == ready.state.win.loss


def test_a_run_reports_its_graphs_in_its_summary(data, tmp_path):
    """``summary.json`` says how many graphs were captured and replayed (none without CUDA,
    where the step runs eagerly), so a GPU run's figures can be read with them."""
    import json

    from plenoctree.nerf import train

    for graph in (False, True):
        cfg = tiny_cpu_config(data, tmp_path / str(graph), steps=6)
        cfg.fixed_step, cfg.cuda_graph, cfg.val_views = True, graph, 0
        train(cfg, quiet=True)
        got = json.loads((tmp_path / str(graph) / "summary.json").read_text())["cuda_graphs"]
        assert got == ({"captures": 0, "replays": 0} if graph else None), got


def _record_step(tr, bar) -> list:
    """The ops of one iteration (with ``cuda_graph``: of the body a graph captures): name,
    and per argument its shape and dtype (tensors; with the address for tensors made before
    the step: a replay reads those addresses) or its value (anything else)."""
    from torch.utils._python_dispatch import TorchDispatchMode

    made: set[int] = set()

    def desc(x):
        if isinstance(x, torch.Tensor):
            ptr = x.untyped_storage().data_ptr() if x.numel() else 0
            where = "inside" if ptr in made or ptr == 0 else ptr
            return ("T", tuple(x.shape), str(x.dtype), x.storage_offset(), where)
        if isinstance(x, (list, tuple)):
            return tuple(desc(y) for y in x)
        return x if isinstance(x, (int, float, bool, str, type(None))) else type(x).__name__

    ops: list = []

    class Rec(TorchDispatchMode):
        def __torch_dispatch__(self, func, types, args=(), kwargs=None):
            sig = (func.overloadpacket.__name__, desc(list(args)),
                   desc(sorted((kwargs or {}).items())))
            out = func(*args, **(kwargs or {}))
            for t in (out if isinstance(out, (list, tuple)) else [out]):
                if isinstance(t, torch.Tensor) and t.numel():
                    made.add(t.untyped_storage().data_ptr())
            ops.append(sig)
            return out

    if tr.graphs is None:                   # the whole step
        with Rec():
            tr.iteration(bar)
        return ops
    body = tr.graphs.body                   # what a graph captures (the rest runs eagerly)

    def recorded(n):
        with Rec():
            return body(n)
    tr.graphs.body = recorded
    try:
        tr.iteration(bar)
    finally:
        tr.graphs.body = body
    return ops


@pytest.mark.parametrize("graph", [True, False])
def test_two_steps_launch_the_same_ops_on_the_same_tensors(data, tmp_path, triton_cpu, graph):
    """What a captured graph replays: the step's ops, their shapes and Python arguments, and
    the addresses of the tensors it reads from outside (parameters, gradients, Adam's state,
    the learning rate, the occupancy grid, the photos) are the same at two steps of one ray
    count. Without ``cuda_graph`` they are not: Adam reads the learning rate as a Python
    number that changes every step (the test can fail)."""
    sys.path.insert(0, str(_BENCH))
    import step_ops

    from plenoctree._util import progress

    tr = _trainer(data, tmp_path / "run", graph)
    tr.cfg.sparsity_points = 256
    bar = progress(total=1, disable=True)
    for _ in range(3):
        tr.iteration(bar)
    with step_ops.backends_of("cuda"):
        tr.iteration(bar)                   # once per process: the hash grid's layout
        seen = []
        for _ in range(2):
            tr.step = step_ops._step_number(tr.step + 1, tr.cfg, False)
            tr.state.n_rays = 512.0
            seen.append(_record_step(tr, bar))
    a, b = seen
    assert len(a) == len(b) > 50
    diff = [(x, y) for x, y in zip(a, b) if x != y]
    if graph:
        assert not diff, diff[:3]
    else:
        assert diff and all("adam" in x[0] for x, _ in diff), [x[0] for x, _ in diff]


class _FakeGraph:
    """CUDA's graph calls stood in for: the capture runs the body once (as a real capture
    records it without running it, the test's body counts how often it ran) and a replay
    runs the recorded body again."""

    made: list = []

    def __init__(self):
        self.body = None
        self.generators = []
        _FakeGraph.made.append(self)

    def register_generator_state(self, gen):
        self.generators.append(gen)

    def replay(self):
        self.body()


class _FakeCapture:
    def __init__(self, g):
        self.g = g

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False


def test_step_graphs_warm_up_capture_once_per_ray_count_and_keep_four(monkeypatch):
    calls, out = [], torch.zeros(2)

    def body(n):
        calls.append(n)
        out.fill_(float(len(calls)))        # a graph's output: overwritten by every replay
        return out, 10 * n

    sg = G.StepGraphs(body, torch.device("cpu"), ("gen",))
    sg.capture = True
    current = {}

    def capture(g):
        current["g"] = g
        return _FakeCapture(g)

    monkeypatch.setattr(torch.cuda, "CUDAGraph", _FakeGraph)
    monkeypatch.setattr(torch.cuda, "graph", capture)
    monkeypatch.setattr(G.StepGraphs, "_eager", lambda self, n: (lambda o, e: (o.clone(), e))(
        *self.body(n)))
    orig_capture = G.StepGraphs._capture

    def capture_and_bind(self, n, e):
        orig_capture(self, n, e)
        e.graph.body = lambda: self.body(n)   # what the recorded graph would replay
    monkeypatch.setattr(G.StepGraphs, "_capture", capture_and_bind)
    _FakeGraph.made = []
    got = [sg.step(256) for _ in range(G.WARMUP + 3)]
    assert len(_FakeGraph.made) == 1 and sg.captures == 1 and sg.replays == 3
    assert _FakeGraph.made[0].generators == ["gen"]
    assert [o for o, _ in got][0] is not out and all(e == 2560 for _, e in got)
    values = [float(o[0]) for o, _ in got]
    assert values == sorted(set(values)), values          # copies, not the overwritten buffer
    for n in (512, 768, 1024, 1280):                      # four more ray counts
        for _ in range(G.WARMUP + 1):
            sg.step(n)
    assert sg.captures == 5 and len(sg.entries) == G.KEEP and 256 not in sg.entries
    sg.step(256)                                          # dropped: warms up again
    assert sg.captures == 5 and sg.entries[256].runs == 1
