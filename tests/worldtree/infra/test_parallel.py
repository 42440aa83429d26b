"""ordered_map: input order, same results as a plain loop, errors at their item, bounded and cancellable."""

from __future__ import annotations

import random
import threading
import time

import pytest

from worldtree.infra.cores import available_cores
from worldtree.infra.parallel import ordered_map, resolve_threads


def _slow_square(x: int) -> int:
    # Random sleeps make items finish out of order, so the order of the results is the function's doing.
    time.sleep(random.Random(x).uniform(0.0, 0.01))
    return x * x


@pytest.mark.parametrize("threads", [1, 2, 5])
def test_results_in_input_order(threads):
    items = list(range(40))
    assert list(ordered_map(_slow_square, items, threads)) == [x * x for x in items]


def test_one_thread_runs_inline():
    names = list(ordered_map(lambda _: threading.current_thread().name, range(3), 1))
    assert names == [threading.current_thread().name] * 3


def test_pool_runs_items_at_once():
    # Two items that each wait for the other to start can only finish on two threads at once.
    started = threading.Barrier(2, timeout=5)

    def meet(x):
        started.wait()
        return x

    assert list(ordered_map(meet, [1, 2], 2)) == [1, 2]


def _recording(fail_at: int | None = None):
    """``(f, calls)``: ``f(x)`` records x in ``calls`` (thread-safe), raises at ``fail_at``, else sleeps briefly
    and returns x."""
    calls: list[int] = []
    lock = threading.Lock()

    def f(x):
        with lock:
            calls.append(x)
        if x == fail_at:
            raise ValueError(f"item {x}")
        time.sleep(0.002)
        return x

    return f, calls


def test_error_is_raised_at_its_item_and_the_rest_is_not_run():
    f, calls = _recording(fail_at=3)
    got = []
    with pytest.raises(ValueError, match="item 3"):
        for r in ordered_map(f, range(1000), 2):
            got.append(r)
    assert got == [0, 1, 2]
    # At most 2 * threads items were in flight when item 3 failed, plus the refills while 0..2 came back.
    assert len(calls) <= 3 + 2 * 2 + 1


def test_stopping_early_cancels_what_has_not_started():
    f, calls = _recording()
    gen = ordered_map(f, range(1000), 3)
    assert [next(gen) for _ in range(5)] == [0, 1, 2, 3, 4]
    gen.close()
    n = len(calls)
    time.sleep(0.05)
    assert len(calls) == n <= 5 + 2 * 3


def test_resolve_threads_follows_torch_within_the_affinity_mask():
    import torch

    before = torch.get_num_threads()
    try:
        assert resolve_threads(3) == 3
        torch.set_num_threads(1)
        assert resolve_threads(0) == 1
        torch.set_num_threads(available_cores() + 4)
        assert resolve_threads(0) == available_cores()
    finally:
        torch.set_num_threads(before)
