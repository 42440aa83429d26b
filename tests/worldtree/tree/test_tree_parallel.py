"""Parallel layer runner: same results as sequential, files handed over, timings, failures, resume."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest
import torch

from benchmarks.fixtures.toy_nodes import fit_node, flags_node, make_input
from tests.worldtree.infra.scripted_machine import Machine
from worldtree.tree.parallel import LayerFailed, LayerRunner, ParallelConfig, node_dir, write_input

NODES = [4, 5, 6, 7]


def _write_layer(folder, steps=150):
    for j in NODES:
        write_input(folder, j, make_input(dim=8, rows=64, steps=steps, seed=100 + j))


def test_tree_parallel_equals_sequential_with_files_and_timings(tmp_path):
    seq_dir, par_dir = tmp_path / "seq", tmp_path / "par"
    _write_layer(seq_dir)
    _write_layer(par_dir)
    seeds = [11, 12, 13, 14]
    with LayerRunner(ParallelConfig(sequential=True, device="cpu"), "benchmarks.fixtures.toy_nodes:fit_node") as r:
        seq = r.run_layer(2, seq_dir, NODES, seeds)
        seq_out = {j: r.load_output(seq_dir, j) for j in NODES}
    threads_here = torch.get_num_threads()
    with LayerRunner(ParallelConfig(device="cpu", max_workers=2, threads_total=2), fit_node) as r:
        r.warm_up(len(NODES))  # workers start now; the layer then reuses them
        pool = r._pool
        assert pool is not None and r._workers == 2
        par = r.run_layer(2, par_dir, NODES, seeds)
        assert r._pool is pool
        par_out = {j: r.load_output(par_dir, j) for j in NODES}
        # Resume: the same inputs are skipped, a changed input is re-run.
        write_input(par_dir, 7, make_input(dim=8, rows=64, steps=10, seed=1))
        again = r.run_layer(2, par_dir, NODES, seeds)
    assert torch.get_num_threads() == threads_here  # the sequential run restored the caller's settings
    assert seq.mode == "sequential" and par.mode == "parallel" and par.workers == 2
    for j in NODES:
        assert torch.equal(seq_out[j]["w"], par_out[j]["w"]), j
        assert seq_out[j]["loss"] == par_out[j]["loss"] and par_out[j]["node"] == j
        assert (node_dir(par_dir, j) / "output.pt").is_file()
        rep = json.loads((node_dir(par_dir, j) / "report.json").read_text())
        assert rep["node"] == j and rep["wall_s"] > 0 and rep["error"] is None
    # Two workers sharing 2 threads: one each. Node 7's re-run was the only node left: in-process, 2 threads.
    assert [n.threads for n in par.nodes] == [1, 1, 1, 1]
    assert again.mode == "in-process" and again.nodes[3].threads == 2
    # Different nodes got different results (seeds and inputs matter), and training did reduce the loss.
    assert not torch.equal(par_out[4]["w"], par_out[5]["w"])
    assert all(par_out[j]["loss"] < 1.0 for j in NODES)
    # Parallel nodes ran in worker processes, sequential ones here.
    assert {n.pid for n in par.nodes}.isdisjoint({n.pid for n in seq.nodes})
    assert len({n.pid for n in par.nodes}) <= 2
    assert all(n.wall_s > 0 for n in seq.nodes + par.nodes) and par.wall_s > 0 and seq.wall_s > 0
    layer = json.loads((par_dir / "layer.json").read_text())
    assert [n["node"] for n in layer["nodes"]] == NODES and layer["depth"] == 2
    assert [n.skipped for n in again.nodes] == [True, True, True, False]


def test_tree_parallel_failure_names_the_node(tmp_path):
    folder = tmp_path / "layer1"
    for j in (2, 3):
        write_input(folder, j, make_input(dim=4, rows=16, steps=5, seed=j))
    with LayerRunner(ParallelConfig(sequential=True, device="cpu"), "benchmarks.fixtures.toy_nodes:fail_node") as r:
        with pytest.raises(LayerFailed, match=r"node\(s\) 3 failed.*toy failure on purpose") as info:
            r.run_layer(1, folder, [2, 3])
    assert [n.node for n in info.value.failed] == [3]
    assert (node_dir(folder, 2) / "output.pt").is_file()
    assert not (node_dir(folder, 3) / "output.pt").exists()


def test_tree_parallel_rejects_unpicklable_functions_and_missing_inputs(tmp_path):
    with pytest.raises(ValueError, match="top-level"):
        LayerRunner(ParallelConfig(device="cpu"), lambda p, c: p)
    with pytest.raises(ValueError, match="module:function"):
        LayerRunner(ParallelConfig(device="cpu"), "no_colon_here")
    with LayerRunner(ParallelConfig(device="cpu"), fit_node) as r, pytest.raises(FileNotFoundError):
        r.run_layer(1, tmp_path, [2, 3])


def test_tree_parallel_dead_worker_is_reported_with_its_node(tmp_path):
    folder = tmp_path / "layer1"
    for j in (2, 3):
        write_input(folder, j, make_input(dim=4, rows=16, steps=5, seed=j))
    cfg = ParallelConfig(device="cpu", max_workers=2, threads_total=2)
    with LayerRunner(cfg, "benchmarks.fixtures.toy_nodes:die_node") as r:
        with pytest.raises(LayerFailed, match="died") as info:
            r.run_layer(1, folder, [2, 3])
        assert 3 in [n.node for n in info.value.failed]
        assert r._pool is None  # the broken pool was dropped


def test_warm_up_pays_the_first_optimizer_import_in_the_worker():
    # A fresh process (as a spawned worker is): torch._dynamo, which the first torch optimizer imports, is loaded
    # by the warm-up, not left for the first node's training.
    code = (
        "import sys\n"
        "from worldtree.tree import parallel\n"
        "before = 'torch._dynamo' in sys.modules\n"
        "parallel._warm('json:dumps')\n"
        "print(before, 'torch._dynamo' in sys.modules)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["False", "True"]


def test_cpu_workers_train_with_deterministic_kernels(tmp_path):
    """A node trained in a worker process must be as reproducible as the run itself: the worker switches
    torch's deterministic algorithms on for a CPU device whatever the parent process had set (here: off, as
    conftest leaves every test)."""
    assert not torch.are_deterministic_algorithms_enabled()
    _write_layer(tmp_path)
    with LayerRunner(ParallelConfig(device="cpu", max_workers=2, threads_total=2), flags_node) as r:
        rep = r.run_layer(2, tmp_path, NODES, [1, 2, 3, 4])
        out = {j: r.load_output(tmp_path, j) for j in NODES}
    assert rep.mode == "parallel"
    assert all(out[j]["deterministic"] is True for j in NODES)


def test_leaving_on_an_interrupt_stops_the_nodes_in_flight():
    # Ctrl-C or SIGTERM while a layer trains: the workers are terminated, not waited for (a node can take an
    # hour at full size); the node starts again from its input on resume.
    import time

    runner = LayerRunner(ParallelConfig(device="cpu", max_workers=2, threads_total=2), fit_node)
    pool = runner._pool_for(2)
    busy = pool.submit(time.sleep, 120)
    procs = list(pool._processes.values())
    runner.__exit__(KeyboardInterrupt, KeyboardInterrupt(), None)
    assert runner._pool is None and procs and not any(p.is_alive() for p in procs)
    assert busy.cancelled() or busy.exception(timeout=0) is not None  # it never finished its 120 s


def test_a_node_run_here_restores_the_count_the_run_is_meant_to_have(tmp_path, monkeypatch):
    # Under load the governor had lowered the team to one thread; a node trained in this process uses every core
    # and ticks the governor; afterwards the run's own count (the ceiling, 2) must be restored, not the lowered 1,
    # which the governor would then take as the new ceiling and keep after the load ends.
    from worldtree.infra import thread_governor as tg
    from worldtree.tree import parallel

    threads_here = torch.get_num_threads()
    m = Machine()
    torch.set_num_threads(2)
    try:
        g = m.governor(torch_threads=True)
        monkeypatch.setattr(tg, "_governor", g)
        monkeypatch.setattr(tg, "_enabled", True)
        g.tick()
        m.others = 1.0
        m.advance(1.0)
        assert g.tick() == 1 and torch.get_num_threads() == 1  # lowered under load

        node_run = parallel._run_node

        def ticking_node(*args, **kwargs):
            m.advance(1.0)
            tg.tick()  # as a trainer's step does, while the node runs on every core
            return node_run(*args, **kwargs)

        monkeypatch.setattr(parallel, "_run_node", ticking_node)
        folder = tmp_path / "layer"
        write_input(folder, 0, make_input(dim=8, rows=16, steps=5, seed=3))
        with LayerRunner(ParallelConfig(sequential=True, device="cpu"), fit_node) as r:
            r.run_layer(1, folder, [0], [1])
        assert torch.get_num_threads() == 2 and tg.intended_threads() == 2
        m.others = 0.0  # the load has ended
        m.advance(1.0)
        assert g.tick() == 2 and g.ceiling == 2
    finally:
        torch.set_num_threads(threads_here)
