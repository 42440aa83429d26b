"""Summarise a sampling profile of a whole run (py-spy's collapsed stacks) by kind of work and by stage.

    py-spy record --rate 100 --subprocesses --format raw -o run.txt -- \\
        wtbench run --method worldtree --scene demo/scenes/SynthBalloon --preset quick
    python -m benchmarks.speed.sampled run.txt [--top 15]

py-spy (``pip install py-spy``; not a dependency of the toolkit) samples every thread of the run and of its
tree-worker processes without slowing them, unlike :mod:`benchmarks.speed.e2e`'s deterministic profiler,
which adds a few microseconds per Python call. Each sample is a stack; this script gives it to the innermost
kind of work on it (the kinds of :data:`benchmarks.speed.e2e.KINDS`: rasterizer forward/backward, projection,
motion and dual-quaternion skinning, losses, motion regularisers, optimiser, densification, autograd's own
backward of torch operators, plus imports and waiting), and to the outermost method stage on it, and prints
the share of samples of each. A sample whose innermost Python frame is a torch operator is counted where that
operator was called from, because py-spy shows Python frames only (native frames need ``--native``).
"""

from __future__ import annotations

import argparse
import re
import sys
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

from benchmarks.speed.e2e import KINDS
from worldtree.infra.errors import UserError

# Extra kinds a whole run has besides the training step's (checked after KINDS, innermost first as well).
EXTRA_KINDS: list[tuple[str, str, tuple[str, ...] | None]] = [
    ("priors", "worldtree/priors/", None),
    ("imports", "<frozen importlib", None),
    ("waiting", "threading.py", ("Condition.wait", "Event.wait")),
    ("waiting", "selectors.py", None),
    ("waiting", "multiprocessing/connection.py", None),
]

_FRAME = re.compile(r"^(?P<name>.*?) \((?P<file>[^()]*?)(?::(?P<line>\d+))?\)$")
_STAGE = re.compile(r"worldtree/(?P<package>stages|tree)/(?P<module>\w+)\.py")
# py-spy --subprocesses puts 'process PID:"COMMAND LINE"' frames first (parent, then child); the command line may itself hold ';'.
_PROCESS = re.compile(r'^process \d+:"(?P<cmd>.*?)";')


@dataclass
class Summary:
    """Sample counts of one profile."""

    total: int = 0
    kinds: Counter = field(default_factory=Counter)
    stages: Counter = field(default_factory=Counter)
    processes: Counter = field(default_factory=Counter)
    leaves: Counter = field(default_factory=Counter)


def _kind(frame: str) -> str | None:
    m = _FRAME.match(frame)
    name, file = (m["name"], m["file"]) if m else (frame, "")
    file = file.replace("\\", "/")
    for kind, where, names in (*KINDS, *EXTRA_KINDS):
        if where in file and (names is None or name in names):
            return kind
    return None


def summarise(lines: list[str]) -> Summary:
    """Counts of collapsed stacks ``frame;frame;...;frame COUNT`` (outermost first) by kind, stage, process."""
    out = Summary()
    for i, line in enumerate(lines, 1):
        line = line.strip()
        if not line:
            continue
        stack, _, count = line.rpartition(" ")
        if not stack or not count.isdigit():
            raise UserError(f"line {i}: not a collapsed stack 'frame;...;frame COUNT'; record with py-spy --format raw")
        n = int(count)
        process = "main"
        while m := _PROCESS.match(stack):  # a worker's stack starts with its parent's process frame
            process = "tree worker" if "multiprocessing" in m["cmd"] else "main"
            stack = stack[m.end() :]
        frames = stack.split(";")
        out.total += n
        out.processes[process] += n
        kind = next((k for f in reversed(frames) if (k := _kind(f)) is not None), "other Python")
        out.kinds[kind] += n
        stage = next(
            (("tree" if m["package"] == "tree" else m["module"]) for f in frames if (m := _STAGE.search(f))),
            "outside the stages",
        )
        out.stages[stage] += n
        if frames:
            out.leaves[frames[-1]] += n
    return out


def report(s: Summary, top: int) -> str:
    """Printable shares of ``s``."""
    if s.total == 0:
        return "no samples"

    def block(title: str, counts: Counter, limit: int | None = None) -> list[str]:
        rows = [title]
        for key, n in counts.most_common(limit):
            rows.append(f"  {100.0 * n / s.total:5.1f} %  {key}")
        return rows

    lines = [f"{s.total} samples"]
    lines += block("by process:", s.processes)
    lines += block("by kind of work (innermost on the stack):", s.kinds)
    lines += block("by stage (module of the outermost worldtree/stages frame; worldtree/tree is 'tree'):", s.stages)
    lines += block(f"innermost Python frames, top {top}:", s.leaves, top)
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("profile", type=Path, help="py-spy record --format raw output")
    ap.add_argument("--top", type=int, default=15, help="innermost frames listed")
    a = ap.parse_args(argv)
    try:
        if not a.profile.is_file():
            raise UserError(f"{a.profile}: no such file; record one with py-spy record --format raw -o FILE -- CMD")
        print(report(summarise(a.profile.read_text().splitlines()), a.top))
    except UserError as e:
        print(f"error: {e}", file=sys.stderr)
        raise SystemExit(2) from None


if __name__ == "__main__":
    main()
