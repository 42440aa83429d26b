"""`--set KEY=VALUE` parsing (methods.config_overrides): every supported annotation, nested frozen
dataclasses, errors naming the key, __post_init__ checks, and the run-folder tag of a set list."""

from __future__ import annotations

import dataclasses
import hashlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import pytest

from benchmarks.runner.runs import run_tag
from methods.config_overrides import apply_overrides, canonical_sets, sets_digest
from methods.registry import get_method
from worldtree.infra.errors import UserError


@dataclass(frozen=True)
class Leaf:
    threshold: float = 1.5
    count: int = 3
    name: str = "a"
    flag: bool = False
    limit: float | None = None
    label: str | None = "x"
    mode: Literal["fast", "medium"] = "medium"
    offsets: tuple[int, ...] = (1, 3)
    tags: tuple[str, ...] = ()
    rgb: tuple[float, float, float] = (0.0, 0.0, 0.0)
    where: Path = Path("/tmp")

    def __post_init__(self) -> None:
        if self.count < 0:
            raise ValueError(f"count {self.count} must be >= 0")


@dataclass(frozen=True)
class Middle:
    leaf: Leaf = field(default_factory=Leaf)
    other: Leaf = field(default_factory=lambda: Leaf(name="other"))
    size: int = 8


@dataclass
class Top:
    steps: int = 10
    mid: Middle = field(default_factory=Middle)


@pytest.mark.parametrize(
    ("item", "path", "expected"),
    [
        ("steps=42", ("steps",), 42),
        ("steps=30_000", ("steps",), 30000),
        ("mid.size=-2", ("mid", "size"), -2),
        ("mid.leaf.threshold=0.25", ("mid", "leaf", "threshold"), 0.25),
        ("mid.leaf.threshold=1e-3", ("mid", "leaf", "threshold"), 0.001),
        ("mid.leaf.threshold=2", ("mid", "leaf", "threshold"), 2.0),
        ("mid.leaf.name=hello world", ("mid", "leaf", "name"), "hello world"),
        ("mid.leaf.name=", ("mid", "leaf", "name"), ""),
        ("mid.leaf.limit=none", ("mid", "leaf", "limit"), None),
        ("mid.leaf.limit=NULL", ("mid", "leaf", "limit"), None),
        ("mid.leaf.limit=0.5", ("mid", "leaf", "limit"), 0.5),
        ("mid.leaf.label=None", ("mid", "leaf", "label"), None),
        ("mid.leaf.label=/data/masks", ("mid", "leaf", "label"), "/data/masks"),
        ("mid.leaf.mode=fast", ("mid", "leaf", "mode"), "fast"),
        ("mid.leaf.offsets=1,2, 5", ("mid", "leaf", "offsets"), (1, 2, 5)),
        ("mid.leaf.offsets=7", ("mid", "leaf", "offsets"), (7,)),
        ("mid.leaf.offsets=", ("mid", "leaf", "offsets"), ()),
        ("mid.leaf.tags=ba,sw", ("mid", "leaf", "tags"), ("ba", "sw")),
        ("mid.leaf.rgb=1,0.5,0", ("mid", "leaf", "rgb"), (1.0, 0.5, 0.0)),
        ("mid.leaf.where=/x/y", ("mid", "leaf", "where"), Path("/x/y")),
        (" mid.leaf.count = 5 ", ("mid", "leaf", "count"), 5),
    ],
)
def test_values_parse_by_annotation(item, path, expected):
    out = apply_overrides(Top(), [item])
    value = out
    for name in path:
        value = getattr(value, name)
    assert value == expected and type(value) is type(expected)


@pytest.mark.parametrize(
    ("raw", "expected"),
    [("true", True), ("True", True), ("1", True), ("yes", True), ("on", True),
     ("false", False), ("FALSE", False), ("0", False), ("no", False), ("off", False)],
)  # fmt: skip
def test_bool_spellings(raw, expected):
    base = Top(mid=Middle(leaf=Leaf(flag=not expected)))
    assert apply_overrides(base, [f"mid.leaf.flag={raw}"]).mid.leaf.flag is expected


@pytest.mark.parametrize(
    ("item", "expected_type"),
    [
        ("steps=1.5", "expected int"),
        ("steps=ten", "expected int"),
        ("mid.leaf.threshold=abc", "expected float"),
        ("mid.leaf.threshold=nan", "expected float"),
        ("mid.leaf.flag=maybe", "expected true/false"),
        ("mid.leaf.limit=abc", "expected float or none"),
        ("mid.leaf.mode=slow", "expected one of fast, medium"),
        ("mid.leaf.offsets=1,x", "expected comma-separated int values"),
        ("mid.leaf.rgb=1,0", "expected 3 comma-separated values"),
    ],
)
def test_bad_value_names_key_type_and_value(item, expected_type):
    key, _, raw = item.partition("=")
    with pytest.raises(UserError) as info:
        apply_overrides(Top(), [item])
    msg = str(info.value)
    assert f"--set {key}=" in msg and expected_type in msg and repr(raw) in msg and "\n" not in msg


def test_nested_frozen_replacement_keeps_everything_else():
    original = Top()
    out = apply_overrides(original, ["mid.leaf.threshold=0.75", "mid.leaf.count=9", "steps=3"])
    # The input is not mutated (frozen levels could not be; the mutable top must not be either).
    assert original == Top() and original.mid.leaf.threshold == 1.5
    expected = Top(steps=3, mid=Middle(leaf=Leaf(threshold=0.75, count=9)))
    assert out == expected
    assert out.mid.other is original.mid.other  # untouched branches are carried over as they are
    with pytest.raises(dataclasses.FrozenInstanceError):
        out.mid.leaf.count = 1  # still the frozen class


def test_unknown_key_lists_fields_and_closest_match():
    with pytest.raises(UserError) as info:
        apply_overrides(Top(), ["mid.leaf.treshold=1"])
    msg = str(info.value)
    assert "mid.leaf.treshold" in msg and "did you mean 'threshold'" in msg
    assert "fields: count, flag, label, limit, mode, name, offsets, rgb, tags, threshold, where" in msg
    assert "\n" not in msg
    with pytest.raises(UserError, match=r"--set nope: Top has no field 'nope'.*fields: mid, steps"):
        apply_overrides(Top(), ["nope=1"])
    with pytest.raises(UserError, match=r"steps is a single value \(int\), not a group"):
        apply_overrides(Top(), ["steps.x=1"])


def test_whole_nested_dataclass_is_refused():
    with pytest.raises(UserError) as info:
        apply_overrides(Top(), ["mid=3"])
    msg = str(info.value)
    assert "--set mid:" in msg and "group of settings (Middle)" in msg and "mid.leaf" in msg
    with pytest.raises(UserError, match="group of settings"):
        apply_overrides(Top(), ["mid.leaf=1"])


@pytest.mark.parametrize("item", ["noequals", "=3", "a..b=1", "mid.1x=2"])
def test_malformed_items(item):
    with pytest.raises(UserError, match="--set"):
        apply_overrides(Top(), [item])


def test_same_key_twice_is_refused():
    with pytest.raises(UserError, match="more than once"):
        apply_overrides(Top(), ["steps=1", " steps = 2"])


def test_post_init_checks_still_run():
    # A nested frozen dataclass's own __post_init__ (ValueError) comes back as a UserError with the key.
    with pytest.raises(UserError, match=r"--set mid.leaf.count=-1: .*must be >= 0"):
        apply_overrides(Top(), ["mid.leaf.count=-1"])
    # BaseConfig.__post_init__ checks the ablations and folds a stage switched off in its settings into them.
    base = get_method("base").config("smoke")
    with pytest.raises(UserError, match=r"--set ablate=xyz: .*choose among ba, sw"):
        apply_overrides(base, ["ablate=xyz"])
    out = apply_overrides(base, ["ablate=sw"])
    assert out.ablate == ("sw",)
    out = apply_overrides(base, ["ba.enabled=no"])
    assert out.ablate == ("ba",) and out.ba.enabled and out == apply_overrides(base, ["ablate=ba"])


def test_real_method_configs():
    wt = get_method("worldtree").config("smoke")
    out = apply_overrides(
        wt,
        [
            "photometric.lambda_depth=0.125",
            "priors.epi.threshold_px=1.0",
            "priors.masks_source=/data/masks",
            "priors.flow.preset=fast",
            "priors.depth.near=none",
            "layer_steps=30,20,10",
            "chain_length=null",
            "scaffold_fit.steps=7",
        ],
    )
    assert out.photometric.lambda_depth == 0.125 and out.priors.epi.threshold_px == 1.0
    assert out.priors.masks_source == "/data/masks" and out.priors.flow.preset == "fast"
    assert out.priors.depth.near is None and out.layer_steps == (30, 20, 10) and out.chain_length is None
    assert out.scaffold_fit.steps == 7
    assert type(out) is type(wt) and wt.priors.epi.threshold_px == 1.5  # the preset's object is unchanged
    # Everything not named keeps the preset's value.
    expect = dataclasses.asdict(wt)
    got = dataclasses.asdict(out)
    for section in ("photometric", "priors", "scaffold_fit"):
        expect.pop(section), got.pop(section)
    expect.pop("layer_steps"), got.pop("layer_steps")
    assert got == expect
    with pytest.raises(UserError, match=r"^--set depth=-1: must be >= 0 \(0 = the root only\)$"):
        apply_overrides(wt, ["depth=-1"])  # WorldTreeConfig.__post_init__
    static = get_method("static").config("quick")
    assert apply_overrides(static, ["background=1,1,1"]).background == (1.0, 1.0, 1.0)
    with pytest.raises(UserError, match=r"StaticConfig has no field 'priors'"):
        apply_overrides(static, ["priors.masks_source=/x"])


def test_digest_and_run_tag():
    sets = ["b.c=2", "a=1"]
    expected = hashlib.sha256(b"a=1\nb.c=2").hexdigest()[:8]
    assert canonical_sets(sets) == ["a=1", "b.c=2"]
    assert sets_digest(sets) == expected
    assert sets_digest([" a = 1", "b.c=2 "]) == expected  # spaces around key and value do not count
    plain = run_tag("quick", {"steps": 5})
    with_sets = run_tag("quick", {"steps": 5}, None, sets)
    assert plain == "quick-steps5" and with_sets == f"quick-steps5-set{expected}"
    assert run_tag("quick", {"steps": 5}, None, list(reversed(sets))) == with_sets
    assert run_tag("quick", {"steps": 5}, None, ["a=1", "b.c=3"]) != with_sets
    assert run_tag("quick", {"steps": 5}, None, []) == plain
    opts = {"ablate": ["ba"], "depth": 3}
    tree = get_method("worldtree").options
    assert run_tag("quick", {}, opts, sets, tree) == f"quick-noba-depth3-set{expected}"
    with pytest.raises(ValueError, match="not among the method's options"):
        run_tag("quick", {}, opts, sets)


@pytest.mark.parametrize("method", ["base", "worldtree"])
def test_a_field_the_method_fills_in_is_refused_not_ignored(method):
    cfg = get_method(method).config("quick")
    # The photometric fit's steps come from `steps`; setting the nested copy would rename the run and do nothing.
    with pytest.raises(UserError, match=r"--set photometric.steps=7: this run never reads photometric.steps"):
        apply_overrides(cfg, ["photometric.steps=7"])
    assert apply_overrides(cfg, ["steps=7"]).steps == 7


def _leaves(obj, prefix=""):
    """``(dotted key, value)`` of every leaf setting of a config dataclass (fields it derives, ``init=False``,
    are not settings)."""
    for f in dataclasses.fields(obj):
        if not f.init:
            continue
        v = getattr(obj, f.name)
        if dataclasses.is_dataclass(v):
            yield from _leaves(v, f"{prefix}{f.name}.")
        else:
            yield f"{prefix}{f.name}", v


def _as_text(v) -> str:
    """A value as `--set` spells it."""
    if v is None:
        return "none"
    if isinstance(v, bool):
        return str(v).lower()
    if isinstance(v, tuple):
        return ",".join(_as_text(x) for x in v)
    return repr(v) if isinstance(v, float) else str(v)


def _configs():
    base, wt, static = get_method("base"), get_method("worldtree"), get_method("static")
    on = {"enabled": True}
    yield "static quick", static.config("quick")
    yield "static budget", dataclasses.replace(static.config("quick"), budget=dataclasses.replace(
        static.config("quick").budget, **on))  # fmt: skip
    yield "base quick", base.config("quick")
    yield "base -sw, budget and early stop", dataclasses.replace(
        base.config("smoke"), ablate=("sw",), budget=dataclasses.replace(base.config("smoke").budget, **on),
        early_stop=dataclasses.replace(base.config("smoke").early_stop, **on),
    )  # fmt: skip
    off = base.config("quick")
    yield "base, motion discovery and migration off", dataclasses.replace(
        off, priors=dataclasses.replace(off.priors, motion=dataclasses.replace(off.priors.motion, enabled=False)),
        photometric=dataclasses.replace(off.photometric, migrate_every=0),
    )  # fmt: skip
    yield "base, temporal opacity off", dataclasses.replace(off, dynamic_time_std=0.0)
    yield "worldtree quick", wt.config("quick")
    yield "worldtree depth auto", dataclasses.replace(wt.config("quick"), depth="auto")
    yield "worldtree -tpt", dataclasses.replace(wt.config("quick"), ablate=("tpt",))


@pytest.mark.parametrize("label,cfg", list(_configs()), ids=[label for label, _ in _configs()])
def test_every_set_key_changes_the_run_or_is_refused(label, cfg):
    """Over every leaf key of the config: a key its run never reads (``ignored_settings``) is refused with
    the reason; any other key is applied (its own value given back leaves the config as it was)."""
    ignored = cfg.ignored_settings()
    keys = dict(_leaves(cfg))
    assert set(ignored) <= set(keys), "ignored_settings names keys the config does not have"
    for key, value in keys.items():
        item = f"{key}={_as_text(value)}"
        if key in ignored:
            with pytest.raises(UserError, match=f"this run never reads {key} "):
                apply_overrides(cfg, [item])
        else:
            assert apply_overrides(cfg, [item]) == cfg, item


def test_a_derived_field_has_one_spelling_its_source():
    cfg = get_method("worldtree").config("quick")
    with pytest.raises(
        UserError, match=r"^--set auto_depth: auto_depth follows from depth; set that instead$"
    ):
        apply_overrides(cfg, ["auto_depth=true"])
    auto = apply_overrides(cfg, ["depth=auto"])
    assert auto.depth == "auto" and auto.auto_depth and not apply_overrides(auto, ["depth=2"]).auto_depth
    with pytest.raises(UserError, match=r"^--set depth=deep: expected int or one of auto, got 'deep'$"):
        apply_overrides(cfg, ["depth=deep"])


def test_switching_a_feature_on_in_the_same_command_makes_its_settings_count():
    cfg = get_method("base").config("quick")
    assert not cfg.budget_on()
    with pytest.raises(UserError, match="the Gaussian budget is off; --set budget.enabled=true"):
        apply_overrides(cfg, ["budget.prune_contribution=2.0"])
    # Checked against the final config, in any order of the items.
    out = apply_overrides(cfg, ["budget.prune_contribution=2.0", "budget.enabled=true"])
    assert out.budget.prune_contribution == 2.0 and out.budget_on()
    with pytest.raises(UserError, match="no tree grows"):
        apply_overrides(get_method("worldtree").config("quick"), ["depth=0", "layer_steps=5"])
    with pytest.raises(UserError, match="motion discovery is off"):
        apply_overrides(cfg, ["priors.motion.enabled=false", "priors.motion.threshold=0.3"])
    with pytest.raises(UserError, match="migration is off"):
        apply_overrides(cfg, ["photometric.migrate_residual=0.1", "photometric.migrate_every=0"])
    out = apply_overrides(cfg, ["photometric.migrate_residual=0.1"])
    assert out.photometric.migrate_residual == 0.1
    with pytest.raises(UserError, match="trajectory depth is off"):
        apply_overrides(cfg, ["scaffold.trajectory_depth=false", "scaffold.trajectory_depth_prior=0.01"])
    with pytest.raises(UserError, match="classical depth only"):
        apply_overrides(cfg, ["priors.depth_source=/somewhere", "scaffold.trajectory_depth=false"])
    out = apply_overrides(cfg, ["scaffold.trajectory_depth_prior=0.01"])
    assert out.scaffold.trajectory_depth_prior == 0.01
    # The fitted-import switch means nothing for classical depth or an unfitted import ...
    with pytest.raises(UserError, match="imported depth fitted to the classical one only"):
        apply_overrides(cfg, ["scaffold.trajectory_depth_imported=true"])
    with pytest.raises(UserError, match="imported depth fitted to the classical one only"):
        apply_overrides(cfg, ["priors.depth_source=/somewhere", "scaffold.trajectory_depth_imported=true"])
    # ... and with a fitted import it makes the trajectory-depth settings count again.
    fitted = ["priors.depth_source=/somewhere", "priors.depth_import.fit_scale_shift=true"]
    with pytest.raises(UserError, match="classical depth only"):
        apply_overrides(cfg, [*fitted, "scaffold.trajectory_depth_prior=0.01"])
    out = apply_overrides(cfg, [*fitted, "scaffold.trajectory_depth_imported=true", "scaffold.trajectory_depth_prior=0.01"])
    assert out.scaffold.trajectory_depth_imported and out.scaffold.trajectory_depth_prior == 0.01
    with pytest.raises(UserError, match="temporal opacity is off"):
        apply_overrides(cfg, ["dynamic_time_std=0", "photometric.lr_time_std=0.02"])
    assert apply_overrides(cfg, ["photometric.lr_time_std=0.02"]).photometric.lr_time_std == 0.02


def test_every_setting_is_read_somewhere():
    """A cheap guard against dead settings: every leaf field of every method's config is read as an attribute
    (``.name`` or ``getattr(x, "name")``) somewhere in the code below the CLI. It cannot tell which object is
    read; the refusals above cover settings that exist but are not read by a given run."""
    import ast

    root = Path(__file__).resolve().parents[2]
    read: set[str] = set()
    for folder in ("worldtree", "methods", "benchmarks"):
        for path in (root / folder).rglob("*.py"):
            for node in ast.walk(ast.parse(path.read_text())):
                if isinstance(node, ast.Attribute) and isinstance(node.ctx, ast.Load):
                    read.add(node.attr)
                elif isinstance(node, ast.Call) and getattr(node.func, "id", None) == "getattr":
                    if len(node.args) > 1 and isinstance(node.args[1], ast.Constant):
                        read.add(str(node.args[1].value))
    for label, cfg in _configs():
        unread = [k for k, _ in _leaves(cfg) if k.rsplit(".", 1)[-1] not in read]
        assert unread == [], f"{label}: settings no code reads: {unread}"
