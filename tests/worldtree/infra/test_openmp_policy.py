"""OpenMP wait policy: a short spin then sleep unless the user chose, never over the user's choice, and it
reaches a fresh process's environment before torch starts its OpenMP runtime."""

from __future__ import annotations

import os
import subprocess
import sys

from worldtree.infra.openmp_policy import choose, configure

BOTH = {"OMP_WAIT_POLICY": "PASSIVE", "GOMP_SPINCOUNT": "10000"}


def test_choose_a_short_spin_unless_the_user_chose():
    assert choose({}) == BOTH
    assert choose({"OMP_WAIT_POLICY": "ACTIVE"}) == {}  # the user's setting stands, and nothing beside it
    assert choose({"OMP_WAIT_POLICY": "PASSIVE"}) == {}
    assert choose({"GOMP_SPINCOUNT": "0"}) == {}
    assert choose({"OMP_NUM_THREADS": "1"}) == BOTH


def test_configure_leaves_the_process_alone_once_torch_is_imported():
    import torch  # noqa: F401  (already imported by the test session anyway)

    env: dict[str, str] = {}
    assert configure(env) is None and env == {}


def test_configure_sets_the_variable_before_torch_in_a_fresh_process():
    code = (
        "import os, sys\n"
        "from worldtree.infra import openmp_policy\n"
        "os.getloadavg = lambda: (0.0, 0.0, 0.0)\n"  # an idle machine: the policy does not depend on it
        "env = {}\n"
        "print(sorted(openmp_policy.configure(env).items()) == sorted(env.items()), env.get('OMP_WAIT_POLICY'),\n"
        "      env.get('GOMP_SPINCOUNT'), 'torch' in sys.modules)\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True,
        env={**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)},
    ).stdout.split()  # fmt: skip
    assert out == ["True", "PASSIVE", "10000", "False"]
