"""Train the nodes of one TPT layer concurrently, one worker process each (paper: "parallel optimization").

Nodes of one depth are independent once their parents are trained, so a layer of ``n`` nodes runs as ``n``
tasks on a pool of worker processes (``spawn`` start method; CUDA cannot be used in forked children):

- CPU: ``workers = min(n, max_workers or cores)``; each worker runs ``torch.set_num_threads(max(1, cores //
  workers))`` so the workers together use the cores once instead of oversubscribing them; when the process
  that starts them governs its threads (:mod:`worldtree.infra.thread_governor`), so do the workers, with every
  core as their ceiling: a worker left alone at the end of a layer takes the cores the others freed.
- CUDA with several devices: one worker per device, each bound to its own GPU (a worker takes a device id
  from a queue when it starts); tasks go to whichever worker is free.
- CUDA with one device: the workers share it (``max_workers`` bounds how many nodes sit on it at once).

Hand-over through files: the caller writes each node's input (e.g. the child :class:`NodeState` made by
:func:`worldtree.tree.inherit.split_state`) under ``layer_dir/node<j>/input.pt``; the worker loads it, calls the
node-training function, and writes the result to ``node<j>/output.pt``; both writes are atomic
(:func:`worldtree.tree.node.save_payload`). A ``node<j>/report.json`` records the node's wall time, its input's
sha256 and the worker's device/threads; a node whose output exists with a report for the same input is skipped
(resume). ``sequential=True`` runs the same tasks in-process one after another (all threads), for comparison;
a layer with a single node to run (the root) also runs in-process in parallel mode.

The node-training function is given as ``"package.module:function"`` or a top-level function (pickled by
name). It is called as ``fn(payload, ctx)`` with the loaded input and a :class:`NodeContext`, and returns the
payload to save (plain data: dicts, lists, numbers, strings, tensors). Before the call the worker seeds
``torch``, ``numpy`` and ``random`` with ``ctx.seed``, so a node's result does not depend on the mode.
A node that raises is reported with its index in a :class:`LayerFailed` raised after the other nodes finish.
"""

from __future__ import annotations

import importlib
import json
import multiprocessing as mp
import os
import random
import time
import traceback
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from worldtree.infra import thread_governor
from worldtree.infra.atomic import atomic_write_json
from worldtree.infra.cores import available_cores
from worldtree.infra.determinism import deterministic_for
from worldtree.infra.hashing import sha256_file
from worldtree.tree.node import load_payload, save_payload

__all__ = [
    "LayerFailed",
    "LayerReport",
    "LayerRunner",
    "NodeContext",
    "NodeReport",
    "ParallelConfig",
    "available_cores",
    "node_dir",
    "write_input",
]

NodeFn = Callable[[Any, "NodeContext"], Any]


@dataclass(frozen=True)
class ParallelConfig:
    """How a layer's nodes are run."""

    sequential: bool = False
    """Run the nodes in this process one after another (``--sequential``), for comparison."""
    max_workers: int | None = None
    """Most nodes trained at once; None: the CPU cores (CPU), the GPU count (several GPUs), 2 (one GPU)."""
    threads_total: int | None = None
    """CPU threads shared by the workers; None: the cores this process may use."""
    device: str = "auto"
    """``auto``/``cpu``/``cuda``: where the nodes train (each worker's device is passed in the context)."""
    resume: bool = True
    """Skip a node whose ``output.pt`` exists with a report for the same ``input.pt``."""


@dataclass(frozen=True)
class NodeContext:
    """What the node-training function is told besides its input payload."""

    node: int
    """Tree index of the node."""
    seed: int
    """Seed of the node (already applied to torch/numpy/random before the call)."""
    device: str
    """Device to train on (e.g. ``cpu``, ``cuda:1``)."""
    threads: int
    """Torch CPU threads of this worker."""
    folder: str
    """The node's folder (for checkpoints of a long node)."""


@dataclass
class NodeReport:
    """Outcome of one node."""

    node: int
    wall_s: float
    """Seconds of the node's load + train + save in its worker (0 when skipped)."""
    cpu_s: float
    """CPU seconds (all threads of the process) over the same span: ``cpu_s / wall_s`` is how many cores the
    node actually got (below its threads when the machine is busy)."""
    device: str
    threads: int
    pid: int
    """Process that ran it (the main process in sequential mode)."""
    input_sha256: str
    skipped: bool = False
    """True when a previous run's output was reused (resume)."""
    error: str | None = None
    """Traceback text when the node failed."""


@dataclass
class LayerReport:
    """Outcome of one layer: per-node reports and the layer's wall time (dispatch to last result)."""

    depth: int
    mode: str
    """``parallel``, ``sequential``, or ``in-process`` (parallel mode with a single node to run)."""
    workers: int
    wall_s: float
    nodes: list[NodeReport] = field(default_factory=list)

    @property
    def node_seconds(self) -> float:
        """Sum of the nodes' own wall times (what a sequential run would take without overhead)."""
        return float(sum(r.wall_s for r in self.nodes))

    def to_dict(self) -> dict:
        d = asdict(self)
        d["node_seconds"] = self.node_seconds
        return d


class LayerFailed(RuntimeError):
    """One or more nodes of a layer failed; ``reports`` holds every node's outcome."""

    def __init__(self, depth: int, failed: list[NodeReport], reports: list[NodeReport]):
        self.depth, self.failed, self.reports = depth, failed, reports
        first = failed[0].error.strip().splitlines()[-1] if failed[0].error else "?"
        super().__init__(
            f"tree layer {depth}: node(s) {', '.join(str(r.node) for r in failed)} failed "
            f"(node {failed[0].node}: {first})"
        )


def node_dir(layer_dir: str | Path, node: int) -> Path:
    """Folder of node ``node`` in a layer folder: ``layer_dir/node<j>``."""
    return Path(layer_dir) / f"node{node}"


def _resolve(fn: str | NodeFn) -> NodeFn:
    if callable(fn):
        return fn
    mod, sep, name = str(fn).partition(":")
    if not sep or not mod or not name:
        raise ValueError(f"node function {fn!r}: expected 'package.module:function'")
    return getattr(importlib.import_module(mod), name)


def _fn_ref(fn: str | NodeFn) -> str | NodeFn:
    """A picklable reference: a string as is; a function must be importable by its qualified name."""
    if isinstance(fn, str):
        _resolve(fn)  # fail early in the main process on a bad name
        return fn
    qual = getattr(fn, "__qualname__", "")
    if "<locals>" in qual or "<lambda>" in qual or not getattr(fn, "__module__", None):
        raise ValueError(
            f"node function {fn!r} is not importable by name (lambda or nested); pass a top-level function "
            "or 'package.module:function'"
        )
    return fn


def _terminate_workers(pool: ProcessPoolExecutor) -> None:
    """SIGTERM every worker process of ``pool`` (``terminate_workers`` where Python has it, 3.14+)."""
    stop = getattr(pool, "terminate_workers", None)
    if callable(stop):
        stop()
        return
    for proc in list((getattr(pool, "_processes", None) or {}).values()):
        if proc.is_alive():
            proc.terminate()


# ---------------------------------------------------------------------------------- worker side
_WORKER: dict[str, Any] = {"device": "cpu", "threads": 1}


def _init_worker(threads: int, device_queue, default_device: str, governor_ceiling: int = 0) -> None:
    torch.set_num_threads(threads)
    if governor_ceiling and device_queue is None and default_device == "cpu":
        # Starts at its share; may take every core once the layer's other workers are done.
        thread_governor.enable(ceiling=governor_ceiling)
    dev = default_device
    if device_queue is not None:
        dev = f"cuda:{device_queue.get()}"
        torch.cuda.set_device(torch.device(dev))
    deterministic_for(dev)  # as the run that started this worker
    _WORKER.update(device=dev, threads=threads)


def _seed_all(seed: int) -> None:
    torch.manual_seed(seed)
    # The legacy global generator on purpose: node functions that draw from it get the node's stream.
    np.random.seed(seed % (2**32))  # noqa: NPY002
    random.seed(seed)


def _run_node(
    fn_ref: str | NodeFn, node: int, seed: int, folder: str, device: str, threads: int
) -> NodeReport:
    """Load ``folder/input.pt``, train, save ``folder/output.pt``; never raises (errors go in the report)."""
    t0, c0 = time.perf_counter(), time.process_time()
    inp = Path(folder) / "input.pt"
    for stale in ("output.pt", "report.json"):  # never leave a previous run's result beside a new attempt
        (Path(folder) / stale).unlink(missing_ok=True)
    digest = ""
    try:
        digest = sha256_file(inp)
        fn = _resolve(fn_ref)
        payload = load_payload(inp, "cpu")
        _seed_all(seed)
        ctx = NodeContext(node, seed, device, threads, folder)
        result = fn(payload, ctx)
        save_payload(Path(folder) / "output.pt", result)
        err = None
    except Exception:  # reported with the node index; Ctrl-C still stops the run
        err = traceback.format_exc()
    rep = NodeReport(
        node,
        time.perf_counter() - t0,
        time.process_time() - c0,
        device,
        threads,
        os.getpid(),
        digest,
        False,
        err,
    )
    if err is None:
        atomic_write_json(Path(folder) / "report.json", asdict(rep))
    return rep


def _warm(fn_ref: str | NodeFn) -> int:
    _resolve(fn_ref)  # import the node function's module (and torch) ahead of the first node
    # The first torch optimizer of a process imports torch._dynamo (about 2-3 s of CPU); pay it here, while
    # the root trains, rather than inside the first node's training.
    torch.optim.Adam([torch.zeros(1, requires_grad=True)])
    return os.getpid()


def _run_in_worker(fn_ref: str | NodeFn, node: int, seed: int, folder: str) -> NodeReport:
    return _run_node(fn_ref, node, seed, folder, _WORKER["device"], _WORKER["threads"])


# ---------------------------------------------------------------------------------- main side
class LayerRunner:
    """Runs layers of node tasks; keeps its worker pool between layers (use as a context manager).

    Args:
        cfg: mode, workers, threads, device.
        fn: node-training function (``"module:function"`` or a top-level function), ``fn(payload, ctx)``.
    """

    def __init__(self, cfg: ParallelConfig, fn: str | NodeFn):
        self.cfg = cfg
        self.fn = _fn_ref(fn)
        self._pool: ProcessPoolExecutor | None = None
        self._workers = 0
        dev = cfg.device
        if dev == "auto":
            dev = "cuda" if torch.cuda.is_available() else "cpu"
        self.device_type = torch.device(dev).type
        if self.device_type == "cuda" and not torch.cuda.is_available():
            raise ValueError(f"ParallelConfig.device {cfg.device!r}: CUDA is not available")
        self.gpus = torch.cuda.device_count() if self.device_type == "cuda" else 0
        self.cores = cfg.threads_total or available_cores()

    def __enter__(self) -> LayerRunner:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        # Leaving on an error or a stop (Ctrl-C, SIGTERM): the nodes in flight are not waited for; each
        # restarts from its input on resume.
        self.close(stop_workers=exc_type is not None)

    def close(self, stop_workers: bool = False) -> None:
        """Shut the worker pool down; ``stop_workers``: terminate the workers instead of waiting for the nodes
        they are training."""
        if self._pool is not None:
            if stop_workers:
                _terminate_workers(self._pool)
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None

    def warm_up(self, n_nodes: int) -> None:
        """Start the workers a layer of ``n_nodes`` will use, without waiting (no-op in sequential mode).

        Call it before training the root: spawning the workers and importing torch and the node function's
        module then overlaps the root's training instead of delaying the first parallel layer.
        """
        if self.cfg.sequential or n_nodes <= 1:
            return
        workers = self.planned_workers(n_nodes)
        pool = self._pool_for(workers)
        for _ in range(workers):
            pool.submit(_warm, self.fn)

    def planned_workers(self, n_nodes: int) -> int:
        """Workers a layer of ``n_nodes`` gets in parallel mode."""
        if self.cfg.max_workers is not None:
            cap = self.cfg.max_workers
        elif self.gpus > 1:
            cap = self.gpus
        elif self.gpus == 1:
            cap = 2
        else:
            cap = self.cores
        return max(1, min(n_nodes, cap))

    def _pool_for(self, workers: int) -> ProcessPoolExecutor:
        if self._pool is not None and self._workers >= workers:
            return self._pool
        self.close()
        ctx = mp.get_context("spawn")
        queue = None
        if self.gpus > 1:
            queue = ctx.Queue()
            for k in range(workers):
                queue.put(k % self.gpus)
        default = "cuda:0" if self.gpus == 1 else "cpu"
        threads = max(1, self.cores // workers)
        self._pool = ProcessPoolExecutor(workers, mp_context=ctx, initializer=_init_worker,
                                         initargs=(threads, queue, default,
                                                   self.cores if thread_governor.enabled() else 0))  # fmt: skip
        self._workers = workers
        return self._pool

    def _skip(self, node: int, folder: Path) -> NodeReport | None:
        out, rep, inp = folder / "output.pt", folder / "report.json", folder / "input.pt"
        if not (self.cfg.resume and out.is_file() and rep.is_file()):
            return None
        try:
            old = json.loads(rep.read_text())
        except (OSError, ValueError):
            return None
        if old.get("input_sha256") != sha256_file(inp) or old.get("error"):
            return None
        return NodeReport(node, 0.0, 0.0, str(old.get("device", "")), int(old.get("threads", 0)), os.getpid(),
                          old["input_sha256"], True, None)  # fmt: skip

    def run_layer(
        self, depth: int, layer_dir: str | Path, nodes: Sequence[int], seeds: Sequence[int] | None = None
    ) -> LayerReport:
        """Train ``nodes`` (each with ``layer_dir/node<j>/input.pt`` written) and return the layer's report.

        ``seeds[k]`` is node ``nodes[k]``'s seed (default: the node index). Writes ``layer_dir/layer.json``.
        Raises :class:`LayerFailed` naming the failed nodes after every node has finished.
        """
        layer_dir = Path(layer_dir)
        nodes = [int(j) for j in nodes]
        seeds = list(nodes) if seeds is None else [int(s) for s in seeds]
        if len(seeds) != len(nodes):
            raise ValueError(f"{len(nodes)} nodes but {len(seeds)} seeds")
        for j in nodes:
            if not (node_dir(layer_dir, j) / "input.pt").is_file():
                raise FileNotFoundError(
                    f"{node_dir(layer_dir, j) / 'input.pt'}: write the node's input first"
                )
        t0 = time.perf_counter()
        reports: dict[int, NodeReport] = {}
        todo = []
        for j, s in zip(nodes, seeds, strict=True):
            old = self._skip(j, node_dir(layer_dir, j))
            if old is not None:
                reports[j] = old
            else:
                todo.append((j, s))
        if self.cfg.sequential or len(todo) <= 1:
            # One node (or none) left: nothing to overlap, so skip the process start-up and use every thread.
            mode, workers = ("sequential" if self.cfg.sequential else "in-process"), 1
            dev = "cuda:0" if self.device_type == "cuda" else "cpu"
            for j, s in todo:
                reports[j] = self._run_here(j, s, str(node_dir(layer_dir, j)), dev)
        else:
            mode, workers = "parallel", self.planned_workers(len(todo))
            pool = self._pool_for(workers)
            futs = {
                j: pool.submit(_run_in_worker, self.fn, j, s, str(node_dir(layer_dir, j))) for j, s in todo
            }
            broken = False
            for j, f in futs.items():
                try:
                    reports[j] = f.result()
                except Exception as e:  # the worker process died (killed, out of memory, crashed)
                    broken = True
                    err = f"worker process for node {j} died: {type(e).__name__}: {e}\n"
                    reports[j] = NodeReport(j, 0.0, 0.0, "", 0, -1, "", False, err)
            if broken:
                self.close()  # a broken pool cannot take more work; the next layer starts a new one
        rep = LayerReport(depth, mode, workers, time.perf_counter() - t0, [reports[j] for j in nodes])
        atomic_write_json(layer_dir / "layer.json", rep.to_dict())
        failed = [r for r in rep.nodes if r.error is not None]
        if failed:
            raise LayerFailed(depth, failed, rep.nodes)
        return rep

    def _run_here(self, node: int, seed: int, folder: str, device: str) -> NodeReport:
        # Same seeding as a worker, but restore this process's RNG and thread settings afterwards.
        np_state, py_state = np.random.get_state(), random.getstate()  # noqa: NPY002
        try:
            with thread_governor.threads_for_block(self.cores), torch.random.fork_rng(devices=[]):
                return _run_node(self.fn, node, seed, folder, device, self.cores)
        finally:
            np.random.set_state(np_state)  # noqa: NPY002
            random.setstate(py_state)

    def load_output(self, layer_dir: str | Path, node: int, device: torch.device | str = "cpu") -> Any:
        """The payload a node's function returned (``node<j>/output.pt``)."""
        return load_payload(node_dir(layer_dir, node) / "output.pt", device)


def write_input(layer_dir: str | Path, node: int, payload: Any) -> Path:
    """Write a node's input payload to ``layer_dir/node<j>/input.pt`` atomically; returns the path."""
    path = node_dir(layer_dir, node) / "input.pt"
    save_payload(path, payload)
    return path
