"""A toy node-training function for the parallel layer runner's tests and speed script (not a model).

:func:`fit_node` fits ``w`` [D] to ``y = X w*`` by Adam on random mini-batches drawn from ``torch``'s global
generator (seeded by the runner), so its result depends only on the input and the node's seed. Its steps are
small tensor operations, overhead-bound like a Gaussian-splatting step on the CPU: one core per node is used
about as well as several, which is where running nodes side by side pays.
"""

from __future__ import annotations

import torch

from worldtree.tree.parallel import NodeContext


def make_input(dim: int, rows: int, steps: int, seed: int, batch: int = 32) -> dict:
    """A node input: data ``X`` [rows, dim], ``y`` [rows], and the optimisation settings."""
    g = torch.Generator().manual_seed(seed)
    X = torch.randn(rows, dim, generator=g, dtype=torch.float64)
    w_true = torch.randn(dim, generator=g, dtype=torch.float64)
    return {"X": X, "y": X @ w_true, "steps": int(steps), "batch": int(batch), "lr": 0.05}


def fit_node(payload: dict, ctx: NodeContext) -> dict:
    """Adam on mini-batches; returns ``{"w", "loss", "node", "steps"}`` (``loss``: final full-data MSE)."""
    X, y = payload["X"].to(ctx.device), payload["y"].to(ctx.device)
    w = torch.zeros(X.shape[1], dtype=X.dtype, device=ctx.device, requires_grad=True)
    opt = torch.optim.Adam([w], lr=payload["lr"])
    for _ in range(payload["steps"]):
        idx = torch.randint(0, X.shape[0], (payload["batch"],))
        loss = ((X[idx] @ w - y[idx]) ** 2).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    with torch.no_grad():
        full = float(((X @ w - y) ** 2).mean())
    return {"w": w.detach().cpu(), "loss": full, "node": ctx.node, "steps": payload["steps"]}


def fail_node(payload: dict, ctx: NodeContext) -> dict:
    """Fails on node 3 (tests the failure report); otherwise :func:`fit_node`."""
    if ctx.node == 3:
        raise RuntimeError("toy failure on purpose")
    return fit_node(payload, ctx)


def die_node(payload: dict, ctx: NodeContext) -> dict:
    """Kills its worker process on node 3 (tests the report of a dead worker); otherwise :func:`fit_node`."""
    if ctx.node == 3:
        import os

        os._exit(3)
    return fit_node(payload, ctx)


def perturb_node(payload: dict, ctx: NodeContext) -> dict:
    """A stand-in for training a tree node (tests of :func:`worldtree.tree.build.grow_tree`).

    Adds ``1e-3 * randn`` (torch's global generator, seeded by the runner) to the node's dynamic means and to
    the means of its trainable ancestor copies, and returns a rising per-frame profile ``w[k] = k + 1`` for the
    gradient split of its children.
    """
    from worldtree.tree.build import node_output, read_node_input

    state, depth = read_node_input(payload)
    with torch.no_grad():
        state.dynamic.params["means"].add_(1e-3 * torch.randn_like(state.dynamic.params["means"]))
        for anc in state.chain:
            if anc.trainable:
                anc.dynamic.params["means"].add_(1e-3 * torch.randn_like(anc.dynamic.params["means"]))
    profile = torch.arange(1, state.interval.length + 1, dtype=torch.float64)
    return node_output(state, profile, {"num_dynamic": len(state.dynamic), "depth": depth})


def make_wait_input(seconds: float, chunks: int = 50) -> dict:
    """Input of :func:`wait_node`: total waiting time in seconds, split in ``chunks`` waits."""
    return {"seconds": float(seconds), "chunks": int(chunks)}


def wait_node(payload: dict, ctx: NodeContext) -> dict:
    """A node whose work happens off the CPU (like a node training on an accelerator, where the process waits
    for kernels): ``chunks`` sleeps adding up to ``seconds``, then a tiny seeded result. Shows the runner's
    concurrency and overhead without competing for CPU."""
    import time

    for _ in range(payload["chunks"]):
        time.sleep(payload["seconds"] / payload["chunks"])
    return {"w": torch.randn(4, dtype=torch.float64), "node": ctx.node}
