"""OpenMP wait policy: PASSIVE only on an oversubscribed machine, never over the user's choice, and it reaches a
fresh process's environment before torch starts its OpenMP runtime."""

from __future__ import annotations

import os
import subprocess
import sys

from worldtree.infra.openmp_policy import choose, configure


def test_choose_passive_only_when_oversubscribed_and_unset():
    assert choose(14.0, 2, {}) == "PASSIVE"
    assert choose(2.0, 2, {}) is None  # exactly busy, not oversubscribed
    assert choose(0.3, 2, {}) is None
    assert choose(14.0, 2, {"OMP_WAIT_POLICY": "ACTIVE"}) is None  # the user's setting stands
    assert choose(3.0, 0, {}) == "PASSIVE"  # an unknown CPU count counts as one


def test_configure_leaves_the_process_alone_once_torch_is_imported():
    import torch  # noqa: F401  (already imported by the test session anyway)

    env: dict[str, str] = {}
    assert configure(env) is None and env == {}


def test_configure_sets_the_variable_before_torch_in_a_fresh_process():
    code = (
        "import os, sys\n"
        "from worldtree.infra import openmp_policy\n"
        "os.getloadavg = lambda: (99.0, 0.0, 0.0)\n"
        "env = {}\n"
        "print(openmp_policy.configure(env), env.get('OMP_WAIT_POLICY'), 'torch' in sys.modules)\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True,
        env={**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)},
    ).stdout.split()  # fmt: skip
    assert out == ["PASSIVE", "PASSIVE", "False"]
