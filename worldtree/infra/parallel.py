"""Independent items computed on a pool of threads, their results handed back in input order.

For work that releases the GIL (OpenCV and NumPy kernels: a frame's plane sweep, a frame pair's optical flow).
Each item is computed by one call on one thread, so its result does not depend on the pool's size; only the
order of completion does, and the results come back in input order regardless. At most ``2 * threads`` items
are in flight, so memory stays bounded however many items there are, and a consumer that stops early (an
exception, Ctrl-C) leaves at most that many to finish: the ones not yet started are cancelled.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from typing import TypeVar

from worldtree.infra.cores import available_cores

T = TypeVar("T")
R = TypeVar("R")


def resolve_threads(threads: int) -> int:
    """``threads`` when positive, else the threads this process is given: torch's thread count (which a sweep's
    worker or a Slurm job sets to its share of the CPUs), at most the cores its affinity mask allows."""
    if threads > 0:
        return int(threads)
    import torch

    return max(1, min(available_cores(), torch.get_num_threads()))


def ordered_map(fn: Callable[[T], R], items: Iterable[T], threads: int) -> Iterator[R]:
    """``fn(item)`` for every item, yielded in input order, computed on ``threads`` threads (1: inline, no
    pool). An exception raised by ``fn`` is raised here, at that item's turn."""
    if threads <= 1:
        for it in items:
            yield fn(it)
        return
    pending: deque[Future[R]] = deque()
    source = iter(items)
    pool = ThreadPoolExecutor(max_workers=threads, thread_name_prefix="worldtree")
    try:
        for it in source:
            pending.append(pool.submit(fn, it))
            if len(pending) >= 2 * threads:
                break
        while pending:
            out = pending.popleft().result()
            nxt = next(source, _END)
            if nxt is not _END:
                pending.append(pool.submit(fn, nxt))
            yield out
    finally:
        # Not-yet-started items are dropped; running ones finish (a thread cannot be stopped).
        for f in pending:
            f.cancel()
        pool.shutdown(wait=True, cancel_futures=True)


_END = object()
