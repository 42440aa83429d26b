"""The method options of `wtbench run`, generated from what the registered methods declare.

Each method's :class:`~methods.registry.MethodSpec` names its ablations (``--ablate NAME``, repeatable) and the
config fields it offers as options of their own (``MethodSpec.options``: ``chain_length`` -> ``--chain-length``).
The option's help is the string literal written under the field, prefixed by the methods that have it; its
value is parsed by the field's annotation exactly as ``--set`` parses it (:mod:`methods.config_overrides`),
and a ``bool`` field is a flag that turns it on. Nothing here names a method or a field: a method installed
from another package brings its options with it. The options are generated when typer builds the command line
(the app runs), so the modules that only register commands import no method.
"""

from __future__ import annotations

import inspect
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

from nvidia_ls.config_options import GeneratedCommand, setting_options
from worldtree.infra.typed_config import FIXED, VARIADIC, shape_of

FLAG, LIST, VALUE = "flag", "list", "value"

# Generating the options imports every method (torch included: seconds). The console entry point turns this
# off when the command line runs another command, so that `wtbench --help` and the light commands stay instant.
_GENERATE = True


def skip_generation() -> None:
    """Give the commands built after this call no method options (for a process that will not run them)."""
    global _GENERATE
    _GENERATE = False


@dataclass(frozen=True)
class GeneratedOption:
    """One method option of `wtbench run`."""

    key: str
    """Config field and ``RunRequest.options`` key."""
    annotation: Any
    """The field's type (a ``tuple[X, ...]`` option: ``X`` per value)."""
    kind: str
    """``flag`` (a bool field, turned on), ``list`` (a tuple field, repeatable) or ``value``."""
    help: str

    @property
    def flag(self) -> str:
        return "--" + self.key.replace("_", "-")


def declared_options() -> list[GeneratedOption]:
    """``--ablate`` (when a method has ablations), then every field some method's ``MethodSpec.options`` names,
    in the methods' order (by name) and each method's declared order. Two methods declaring one field with
    different types is a TypeError, as is a field without its help."""
    from benchmarks.runner.runs import ABLATE
    from methods.config_overrides import field_types
    from methods.registry import list_methods
    from nvidia_ls.config_options import field_docs

    specs = list_methods()
    out: list[GeneratedOption] = []
    ablating = [s for s in specs if s.ablations]
    if ablating:
        names = "; ".join(f"{s.name}: {', '.join(s.ablations)}" for s in ablating)
        out.append(
            GeneratedOption(
                ABLATE, tuple[str, ...], LIST, f"Ablate a component, repeat for several ({names})."
            )
        )
    owners: dict[str, list] = {}
    for spec in specs:
        for opt in spec.options:
            owners.setdefault(opt.field, []).append(spec)
    for key, methods in owners.items():
        types = {s.name: field_types(s.config_cls)[key] for s in methods}
        if len(set(map(str, types.values()))) > 1:
            raise TypeError(f"option --{key.replace('_', '-')}: declared with different types {types}")
        doc = field_docs(methods[0].config_cls).get(key)
        if doc is None:
            raise TypeError(
                f"{methods[0].config_cls.__name__}.{key}: write its help as a string literal under it"
            )
        tp = types[methods[0].name]
        kind = FLAG if tp is bool else LIST if shape_of(tp).kind in (VARIADIC, FIXED) else VALUE
        out.append(GeneratedOption(key, tp, kind, f"{', '.join(s.name for s in methods)}: {doc}"))
    return out


def given_options(declared: list[GeneratedOption], values: Mapping[str, Any]) -> dict[str, Any]:
    """The ``RunRequest.options`` of the command-line ``values`` (by key): options not given are left out; a
    flag given is True; a list's values are parsed, sorted and deduplicated (so that one set of ablations names
    one run folder); a value is parsed by its field's type. A value that does not parse is a one-line
    :class:`UserError` naming the option."""
    from methods.config_overrides import parse_value

    out: dict[str, Any] = {}
    for o in declared:
        raw = values.get(o.key)
        if o.kind == FLAG:
            if raw:
                out[o.key] = True
        elif o.kind == LIST:
            if raw:
                item = shape_of(o.annotation).args[0]
                out[o.key] = sorted({parse_value(item, s.strip(), o.key, o.flag) for s in raw})
        elif raw is not None:
            out[o.key] = parse_value(o.annotation, raw.strip(), o.key, o.flag)
    return out


def _typer_parameter(o: GeneratedOption) -> inspect.Parameter:
    import typer

    from methods.config_overrides import describe_type

    if o.kind == FLAG:
        annotation, default = bool, typer.Option(False, o.flag, help=o.help)
    elif o.kind == LIST:
        annotation, default = list[str] | None, typer.Option(None, o.flag, help=o.help, metavar="NAME")
    else:
        arms = describe_type(o.annotation).split(" or ")  # "int or one of auto" -> INT|auto
        metavar = "|".join(a.removeprefix("one of ").replace(", ", "|") if a.startswith("one of ") or a == "none"
                           else a.upper() for a in arms)  # fmt: skip
        annotation, default = str | None, typer.Option(None, o.flag, help=o.help, metavar=metavar)
    return inspect.Parameter(o.key, inspect.Parameter.KEYWORD_ONLY, default=default, annotation=annotation)


class MethodOptionsCommand(GeneratedCommand):
    """A typer command function with the method options added: ``func`` declares its own parameters plus one
    named ``param`` that receives the given options (:func:`given_options`)."""

    def __init__(self, func: Callable[..., Any], param: str = "method_options") -> None:
        super().__init__(func, param)

    def _generate(self) -> tuple[Any, list[inspect.Parameter]]:
        declared = declared_options() if _GENERATE else []
        return declared, [_typer_parameter(o) for o in declared]

    def _collect(self, payload: Any, values: dict[str, Any]) -> Any:
        return given_options(payload, values)

    def _options(self, payload: Any) -> Mapping[str, str]:
        from methods.registry import list_methods

        by_key = {o.key: o.flag for o in payload}
        out: dict[str, str] = {}
        for spec in list_methods() if payload else ():  # no options generated: no method imported
            out |= setting_options(spec.config_cls, by_key)
        return out
