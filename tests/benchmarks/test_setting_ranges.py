"""Every numeric setting has one declared range (worldtree.infra.config_ranges), checked on the resolved config
before any work (issue #30: `lambda_depth=-1` silently meant off, `ba.steps=-10`, `checkpoint_every=0`,
`log_every=-1` were accepted; `downscale=1000`, `priors.flow.offsets=`, a 20-digit --seed failed late)."""

from __future__ import annotations

import dataclasses
import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from benchmarks.runner.runs import RunRequest, execute, resolve_config
from methods.config_overrides import field_types
from methods.registry import get_method, list_methods
from worldtree.infra.config_ranges import Range, config_problems, range_of
from worldtree.infra.errors import UserError


def _numeric_keys(cfg, prefix=""):
    """Dotted keys of the int/float (or tuple of them) leaves of a config, with their field."""
    out = []
    types = field_types(type(cfg))
    for f in dataclasses.fields(cfg):
        v = getattr(cfg, f.name)
        if dataclasses.is_dataclass(v):
            out += _numeric_keys(v, prefix + f.name + ".")
        elif types.get(f.name) in (int, float):
            out.append((prefix + f.name, f))
    return out


def _request(method, preset, sets=(), **kw):
    return RunRequest(scene=".", method=method, preset=preset, sets=list(sets), **kw)


def test_every_preset_is_within_the_declared_ranges():
    for spec in list_methods():
        for preset in spec.presets:
            assert config_problems(spec.config(preset)) == [], (spec.name, preset)


@pytest.mark.parametrize(
    ("method", "item", "needle"),
    [
        ("base", "photometric.lambda_depth=-1", "must be at least 0 (a loss weight"),
        ("base", "ba.steps=-10", "must be at least 0 (a number of steps)"),
        ("base", "checkpoint_every=0", "must be at least 1 (a period in steps)"),
        ("base", "log_every=-1", "must be at least 1"),
        ("base", "sw.strategy.refine_every=0", "must be at least 1"),
        ("base", "priors.flow.offsets=", "needs at least one value"),
        ("base", "photometric.lambda_depth=inf", "must be a finite number"),
        ("base", "photometric.lr_means=-1e-3", "must be at least 0 (a learning rate"),
        ("base", "dynamic_init_opacity=0", "between 0 and 1, both excluded"),
        ("static", "lambda_dssim=-0.5", "must be at least 0"),
        ("static", "sh_degree=4", "between 0 and 3"),
        ("worldtree", "photometric.lambda_track=-1", "must be at least 0"),
        ("base", "priors.threads=-3", "must be at least 0 (a thread count"),
    ],
)
def test_out_of_range_set_is_one_line(method, item, needle):
    with pytest.raises(UserError) as err:
        resolve_config(
            get_method(method), _request(method, "smoke" if method != "static" else "quick", [item])
        )
    msg = str(err.value)
    assert msg.startswith(f"--set {item}: ") and needle in msg and "\n" not in msg


def test_floater_margin_is_a_fraction_strictly_inside_zero_one():
    # The floater test builds the imported depth's check from it (FreeSpaceConfig), which refuses 0 and 1 mid-fit.
    cfg = get_method("base").config("smoke")
    for bad in (0.0, 1.0, 1.5):
        ph = dataclasses.replace(cfg.photometric, floater_tolerance=bad)
        problems = config_problems(dataclasses.replace(cfg, photometric=ph))
        assert [(k, why) for k, _, why in problems] == [
            ("photometric.floater_tolerance", "must be between 0 and 1, both excluded (a relative margin)")
        ], bad
    ph = dataclasses.replace(cfg.photometric, floater_tolerance=0.4)
    assert config_problems(dataclasses.replace(cfg, photometric=ph)) == []


def test_in_range_values_and_zero_meaning_off_are_accepted():
    cfg, _ = resolve_config(
        get_method("base"),
        _request("base", "smoke", ["photometric.lambda_depth=0", "photometric.track_every=0", "ba.steps=0"]),
    )
    assert cfg.photometric.lambda_depth == 0 and cfg.ba.steps == 0


def test_huge_seed_names_the_option():
    with pytest.raises(UserError, match=r"^--seed 12345678901234567890: must be between 0 and 2147483647"):
        resolve_config(
            get_method("static"), _request("static", "quick", overrides={"seed": 12345678901234567890})
        )


def test_declared_metadata_wins_over_the_rules():
    @dataclasses.dataclass
    class C:
        lambda_x: float = dataclasses.field(default=1.0, metadata={"range": Range(2, 3, "odd weight")})

    f = dataclasses.fields(C)[0]
    assert range_of(f) == Range(2, 3, "odd weight")
    assert config_problems(C()) == [("lambda_x", 1.0, "must be between 2 and 3 (odd weight)")]


def test_downscale_too_large_is_refused_before_anything(scene, tmp_path):
    req = RunRequest(scene=scene, method="static", runs_dir=tmp_path / "runs", preset="quick", device="cpu",
                     overrides={"downscale": 1000}, progress=False)  # fmt: skip
    with pytest.raises(UserError, match=r"^--downscale 1000: the 64x36 images .* at most 3$"):
        execute(req)
    assert not (tmp_path / "runs").exists()


_KEYS = [(spec.name, key, f) for spec in list_methods() for key, f in _numeric_keys(spec.config("quick"))]
_VALUES = st.one_of(
    st.integers(min_value=-(10**20), max_value=10**20).map(str),
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.sampled_from(["0", "1", "-1", "1e30", "-1e-30", "inf", "-inf", "nan", "", "1.5", "2"]),
)


@settings(max_examples=400, deadline=None)
@given(st.sampled_from(_KEYS), _VALUES)
def test_every_numeric_setting_is_accepted_in_range_or_refused_in_one_line(key, value):
    method, dotted, field = key
    try:
        cfg, _ = resolve_config(get_method(method), _request(method, "quick", [f"{dotted}={value}"]))
    except UserError as e:
        assert "\n" not in str(e) and str(e).startswith(f"--set {dotted}=")
        return
    assert config_problems(cfg) == []
    got = cfg
    for part in dotted.split("."):
        got = getattr(got, part)
    assert isinstance(got, int | float) and math.isfinite(got)
    rng = range_of(field)
    assert rng is None or rng.problem(got) is None
