"""Same seed, same run: PyTorch's deterministic kernels wherever the run trains on the CPU.

Rule: a process that trains on the CPU (a run, a tree node's worker) switches
:func:`torch.use_deterministic_algorithms` on before its first step. Without it the backward of advanced
indexing (``index_put_`` with accumulation, behind every gather of scaffold nodes and neighbours) adds its
contributions in thread order, and the drift grows through training: two runs of one scene with one seed
ended 0.70 dB PSNR apart (arc rig, 12 frames, root alone; 2026-11-27, docs/worldtree_method.md). With it the
two runs are bit-identical, and not measurably slower (final photometric rate 16.7 and 17.4 it/s, two runs side
by side, against 14.7 and 21.8 it/s without it, also two side by side; a gather's backward alone 11.2 against
11.9 ms).

On CUDA the flag stays off: the rasterizer (gsplat) accumulates gradients with atomics whatever it says, and
cuBLAS would need ``CUBLAS_WORKSPACE_CONFIG`` set before the process starts; a GPU run is reproducible to
within that noise only. ``warn_only`` keeps an operation without a deterministic kernel from stopping a run.
"""

from __future__ import annotations

import torch

__all__ = ["deterministic_for"]


def deterministic_for(device: torch.device | str) -> bool:
    """Switch PyTorch's deterministic algorithms on for a CPU ``device``, off otherwise; returns the setting
    (recorded in the run's ``timing.json``)."""
    on = torch.device(device).type == "cpu"
    torch.use_deterministic_algorithms(on, warn_only=True)
    return on
