"""The allowed range of every numeric config setting, declared once, and the check of a whole config against it.

A setting's range comes from its dataclass field's metadata when it declares one
(``field(default=..., metadata=in_range(0, None, "a loss weight"))``), else from the first rule of ``RULES``
whose pattern matches the field's name: every field of that name, in any method's config, shares the
declaration (``lambda_depth`` is a loss weight wherever it appears). Every number must also be finite.
``wtbench run`` / ``wtbench sweep`` check the resolved config (preset, ``--steps``/``--seed``/``--downscale``
and every ``--set``) with :func:`check_config_ranges` before any work, so ``--set photometric.lambda_depth=-1``
or ``--set checkpoint_every=0`` is refused in one line instead of meaning something else or failing late.
"""

from __future__ import annotations

import dataclasses
import math
import re
from dataclasses import dataclass
from typing import Any

from worldtree.infra.errors import UserError

RANGE_KEY = "range"


@dataclass(frozen=True)
class Range:
    """Closed range ``[lo, hi]`` (None: unbounded; ``open_lo``/``open_hi`` exclude the bound) and what the
    setting is, for the message."""

    lo: float | None = None
    hi: float | None = None
    what: str = ""
    open_lo: bool = False
    open_hi: bool = False
    non_empty: bool = False
    """For a tuple setting: at least one value (each value is checked against the range)."""

    def problem(self, v: float) -> str | None:
        """Why ``v`` is outside the range, or None."""
        lo_bad = self.lo is not None and (v <= self.lo if self.open_lo else v < self.lo)
        hi_bad = self.hi is not None and (v >= self.hi if self.open_hi else v > self.hi)
        if not (lo_bad or hi_bad):
            return None
        return f"must be {self.describe()}" + (f" ({self.what})" if self.what else "")

    def describe(self) -> str:
        """``at least 0``, ``between 0 and 1``, ``above 0``..."""
        lo = None if self.lo is None else _number(self.lo)
        hi = None if self.hi is None else _number(self.hi)
        if lo is not None and hi is not None:
            ends = ("excluded" if self.open_lo else "", "excluded" if self.open_hi else "")
            note = {
                ("", ""): "",
                ("excluded", ""): f", {lo} excluded",
                ("", "excluded"): f", {hi} excluded",
            }.get(ends, ", both excluded")
            return f"between {lo} and {hi}{note}"
        if lo is not None:
            return f"above {lo}" if self.open_lo else f"at least {lo}"
        if hi is not None:
            return f"below {hi}" if self.open_hi else f"at most {hi}"
        return "finite"


def _number(v: float) -> str:
    return str(int(v)) if float(v).is_integer() and abs(v) < 1e15 else f"{v:g}"


def in_range(lo: float | None = None, hi: float | None = None, what: str = "", **kw: Any) -> dict[str, Range]:
    """Field metadata declaring a setting's range: ``field(default=1.0, metadata=in_range(0, None, "..."))``."""
    return {RANGE_KEY: Range(lo, hi, what, **kw)}


SEED_MAX = 2**31 - 1
# Field name pattern -> range; the first match wins. Settings where 0 means "off" say so.
RULES: tuple[tuple[str, Range], ...] = (
    (r"lambda_\w+", Range(0, None, "a loss weight; 0 turns the term off")),
    (r"(lr_\w+|\w+_lr|\w+_lr_scale)", Range(0, None, "a learning rate or its scale; 0 freezes the group")),
    (r"(checkpoint|log|refine|reseed|track_seed|sh_increase)_every", Range(1, None, "a period in steps")),
    (r"\w+_every", Range(0, None, "a period in steps; 0 turns it off")),
    (r"(steps|\w+_steps)", Range(0, None, "a number of steps")),
    (r"downscale", Range(1, None, "an image shrink factor")),
    (r"seed", Range(0, SEED_MAX, "a random seed")),
    (r"threads", Range(0, None, "a thread count; 0 takes torch's")),
    (r"sh_degree", Range(0, 3, "a spherical-harmonics degree")),
    (
        r"(init_opacity|dynamic_init_opacity|inherit_opacity)",
        Range(0, 1, "an opacity", open_lo=True, open_hi=True),
    ),
    (r"(reset_opacity)", Range(0, 1, "an opacity", open_lo=True)),
    (r"prune_opacity", Range(0, 1, "an opacity", open_hi=True)),
    (r"(offsets|track_gaps)", Range(1, None, "frame offsets", non_empty=True)),
    (r"(max_\w+|\w+_max_init|init_num_points|init_max_points)", Range(0, None, "a count")),
    (r"(\w+_px|\w+_units|\w+_frac)", Range(0, None, "a size or fraction")),
)


def range_of(field: dataclasses.Field) -> Range | None:
    """The declared range of a config field (its metadata, else the first matching rule), or None."""
    declared = field.metadata.get(RANGE_KEY) if field.metadata else None
    if declared is not None:
        return declared
    for pattern, rng in RULES:
        if re.fullmatch(pattern, field.name):
            return rng
    return None


def config_problems(cfg: Any, prefix: str = "") -> list[tuple[str, Any, str]]:
    """``(dotted key, value, why)`` of every numeric setting of the config dataclass ``cfg`` (nested ones
    included) outside its range or not finite."""
    out: list[tuple[str, Any, str]] = []
    for f in dataclasses.fields(cfg):
        value = getattr(cfg, f.name)
        key = prefix + f.name
        if dataclasses.is_dataclass(value) and not isinstance(value, type):
            out += config_problems(value, key + ".")
            continue
        rng = range_of(f)
        values = list(value) if isinstance(value, tuple) else [value]
        numbers = [v for v in values if isinstance(v, int | float) and not isinstance(v, bool)]
        if isinstance(value, tuple) and rng is not None and rng.non_empty and not values:
            out.append(
                (key, value, f"needs at least one value ({rng.what})" if rng.what else "needs a value")
            )
            continue
        for v in numbers:
            if not math.isfinite(v):
                out.append((key, value, "must be a finite number"))
                break
            why = rng.problem(v) if rng is not None else None
            if why is not None:
                out.append((key, value, why))
                break
    return out


def check_config_ranges(cfg: Any, flags: dict[str, str] | None = None) -> None:
    """Raise :class:`UserError` for the first setting of ``cfg`` outside its range, naming how it was given:
    ``flags`` maps a dotted key to its option text (``--set KEY=VALUE``, ``--seed N``); other keys are named
    as settings of the preset."""
    problems = config_problems(cfg)
    if not problems:
        return
    key, value, why = problems[0]
    shown = ",".join(str(v) for v in value) if isinstance(value, tuple) else value
    given = (flags or {}).get(key, f"setting {key}={shown} (from the preset)")
    raise UserError(f"{given}: {why}")
