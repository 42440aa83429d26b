"""Every field of every registered method's config can be reached from the command line, and every option a
method declares reaches a field (the wtbench side of the check that caught nvls' dropped ``--sfm-threads``).

A leaf field (a non-dataclass value, at any depth of nested config dataclasses) is reachable when ``--set
PATH=VALUE`` with its own default written as text gives back a config with that value at that path, or, where
the default run never reads it, when the refusal names the gate (the config's ``ignored_settings()`` lists it)
and the field is set once the gate is open. The values are written the way a user types them and parsed by
``methods.config_overrides``; the expected value is the default read back from the dataclass, an independent
route.
"""

from __future__ import annotations

import dataclasses
import enum
from typing import Any

import pytest

from methods.config_overrides import apply_overrides, field_types
from methods.registry import list_methods
from worldtree.infra.errors import UserError

#: Switches that open the settings a default run does not read (a field listed in ``ignored_settings()``).
GATES = {
    "budget.": ["budget.enabled=true"],
    "early_stop.": ["early_stop.enabled=true"],
    "auto_split.": ["depth=auto"],
    "holdout.": ["holdout.enabled=true"],
    "object_depth.": ["priors.masks_source=masks"],
}


def _text(value: Any) -> str:
    """``value`` as typed after ``--set KEY=``."""
    if value is None:
        return "none"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, enum.Enum):
        return str(value.value)
    if isinstance(value, tuple):
        return ",".join(_text(v) for v in value)
    return str(value)  # numbers round-trip through str (repr for floats), paths and text as they are


def _leaves(cfg: Any, prefix: str = "") -> list[tuple[str, Any]]:
    out = []
    for f in dataclasses.fields(cfg):
        if not f.init:
            continue
        v = getattr(cfg, f.name)
        if dataclasses.is_dataclass(v) and not isinstance(v, type):
            out += _leaves(v, f"{prefix}{f.name}.")
        else:
            out.append((f"{prefix}{f.name}", v))
    return out


def _get(cfg: Any, path: str) -> Any:
    for part in path.split("."):
        cfg = getattr(cfg, part)
    return cfg


def _cases():
    for spec in list_methods():
        cfg = spec.config("quick")
        for path, value in _leaves(cfg):
            yield pytest.param(spec.name, path, value, id=f"{spec.name}:{path}")


@pytest.mark.parametrize(("method", "path", "value"), list(_cases()))
def test_every_config_field_is_reachable_with_set(method, path, value):
    spec = next(s for s in list_methods() if s.name == method)
    cfg = spec.config("quick")
    item = f"{path}={_text(value)}"
    ignored = cfg.ignored_settings() if hasattr(cfg, "ignored_settings") else {}
    try:
        got = apply_overrides(cfg, [item])
    except UserError as e:
        # Refused only because the default run does not read it: the refusal says so, the config lists it,
        # and opening its gate makes it settable.
        assert path in ignored and "never reads" in str(e), f"--set {item}: {e}"
        gate = next((g for p, g in GATES.items() if path.startswith(p)), None)
        if gate is None:
            # Filled in by the method from another field: the reason names the option that sets it.
            assert "--" in ignored[path], f"{path}: unreachable ({ignored[path]})"
            return
        got = apply_overrides(cfg, [*gate, item])
    assert _get(got, path) == value, f"--set {item} gave {_get(got, path)!r}"


@pytest.mark.parametrize("spec", list_methods(), ids=lambda s: s.name)
def test_every_declared_option_is_a_top_level_field(spec):
    fields = field_types(spec.config_cls)
    for opt in spec.options:
        assert opt.field in fields, f"{spec.name}: option --{opt.field.replace('_', '-')} names no config field"
