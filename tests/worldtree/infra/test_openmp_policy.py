"""OpenMP wait policy: PASSIVE unless the user chose, never over the user's choice, and it reaches a fresh
process's environment before torch starts its OpenMP runtime."""

from __future__ import annotations

import os
import subprocess
import sys

from worldtree.infra.openmp_policy import choose, configure


def test_choose_passive_unless_the_user_chose():
    assert choose({}) == "PASSIVE"
    assert choose({"OMP_WAIT_POLICY": "ACTIVE"}) is None  # the user's setting stands
    assert choose({"OMP_WAIT_POLICY": "PASSIVE"}) is None
    assert choose({"OMP_NUM_THREADS": "1"}) == "PASSIVE"


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
        "print(openmp_policy.configure(env), env.get('OMP_WAIT_POLICY'), 'torch' in sys.modules)\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True,
        env={**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)},
    ).stdout.split()  # fmt: skip
    assert out == ["PASSIVE", "PASSIVE", "False"]
