"""Command-line options generated from a config dataclass: the dataclass is the one source of defaults and help.

Each field becomes ``--field-name`` (underscores as dashes) with the default of the config made with no
arguments and, as its help, the string literal written under the field (its attribute docstring). A field
holding a dataclass contributes its own fields under its name (``mask.threshold`` -> ``--mask-threshold``).
A boolean that defaults to False is a flag (``--force``); one that defaults to True also gets ``--no-...``.
A command states only what it shows differently (:class:`Shown`: another command-line type with its parser,
other flag names, other help). :class:`ConfigCommand` gives typer a command whose options are these, and hands
the command function the config built from the parsed values, so an option cannot miss its field.

Field types understood without a :class:`Shown`: ``int``, ``float``, ``str``, ``bool``, ``Path``, each optionally
``| None``; any other type needs a :class:`Shown` with a ``type`` and ``parse``.
"""

from __future__ import annotations

import ast
import dataclasses
import functools
import inspect
import textwrap
import typing
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from worldtree.infra.cli_runner import options_named
from worldtree.infra.config_json import from_dict
from worldtree.infra.typed_config import optional_of, setting_paths

SIMPLE_TYPES = (int, float, str, bool, Path)


@dataclass(frozen=True)
class Shown:
    """How one field appears on the command line where the generated default does not fit."""

    type: Any = None
    """Command-line type (typer converts to it), when it differs from the field's type."""
    parse: Callable[[Any], Any] | None = None
    """Command-line value -> field value (needed with ``type``)."""
    decls: tuple[str, ...] = ()
    """Flag names instead of the generated ``--field-name``."""
    help: str | None = None
    """Help instead of the field's docstring (for a command-line form the docstring does not describe)."""


@dataclass(frozen=True)
class ConfigOption:
    """One generated option: where its value goes in the config and how typer declares it."""

    path: tuple[str, ...]
    """Field names from the top config down, e.g. ``("mask", "threshold")``."""
    type: Any
    default: Any
    help: str
    decls: tuple[str, ...]
    parse: Callable[[Any], Any] | None = None

    @property
    def dotted(self) -> str:
        return ".".join(self.path)

    @property
    def param(self) -> str:
        """Python parameter name of the command function, e.g. ``mask_threshold``."""
        return "_".join(self.path)


def field_docs(cls: type) -> dict[str, str]:
    """Attribute docstrings of a dataclass: field name -> the string literal under it, on one line."""
    docs: dict[str, str] = {}
    for klass in reversed(cls.__mro__):
        if not dataclasses.is_dataclass(klass):
            continue
        tree = ast.parse(textwrap.dedent(inspect.getsource(klass)))
        body = tree.body[0].body
        for stmt, nxt in zip(body, body[1:], strict=False):
            if (
                isinstance(stmt, ast.AnnAssign)
                and isinstance(stmt.target, ast.Name)
                and isinstance(nxt, ast.Expr)
                and isinstance(nxt.value, ast.Constant)
                and isinstance(nxt.value.value, str)
            ):
                docs[stmt.target.id] = " ".join(inspect.cleandoc(nxt.value.value).split())
    return docs


def config_options(
    cls: type,
    shown: Mapping[str, Shown] | None = None,
    *,
    _prefix: tuple[str, ...] = (),
    _default: Any = None,
) -> list[ConfigOption]:
    """The options of every field of ``cls`` (nested dataclasses flattened); ``shown`` by dotted field path.

    Raises TypeError for a field whose type has no generated form and no :class:`Shown` type, and KeyError
    for a ``shown`` entry that names no field (so a renamed field cannot leave a stale entry behind)."""
    shown = dict(shown or {})
    default = cls() if _default is None else _default
    hints = typing.get_type_hints(cls)
    docs = field_docs(cls)
    out: list[ConfigOption] = []
    for f in dataclasses.fields(cls):
        path = (*_prefix, f.name)
        dotted = ".".join(path)
        value = getattr(default, f.name)
        tp = hints[f.name]
        if dataclasses.is_dataclass(tp):
            out += config_options(tp, shown, _prefix=path, _default=value)
            continue
        how = shown.get(dotted, Shown())
        cli_type = how.type if how.type is not None else tp
        if how.type is None:
            base, _ = optional_of(tp)
            if base not in SIMPLE_TYPES:
                raise TypeError(f"{cls.__name__}.{f.name}: type {tp} needs a Shown(type=..., parse=...)")
        if how.help is None and f.name not in docs:
            raise TypeError(f"{cls.__name__}.{f.name}: write its help as a string literal under the field")
        flag = "--" + "-".join(path).replace("_", "-")
        if how.decls:
            decls = how.decls
        elif cli_type is bool:
            decls = (flag,) if value is False else (f"{flag}/--no-{flag[2:]}",)
        else:
            decls = (flag,)
        out.append(
            ConfigOption(
                path=path,
                type=cli_type,
                default=value,
                help=how.help if how.help is not None else docs[f.name],
                decls=decls,
                parse=how.parse,
            )
        )
    if not _prefix:
        unknown = set(shown) - {o.dotted for o in out}
        if unknown:
            raise KeyError(f"{cls.__name__}: Shown for no field: {', '.join(sorted(unknown))}")
    return out


def config_from(cls: type, options: Iterable[ConfigOption], values: Mapping[str, Any]) -> Any:
    """The config ``cls`` built from command-line ``values`` (by option ``param``), nested configs included."""
    tree: dict[str, Any] = {}
    for o in options:
        value = values[o.param]
        if o.parse is not None:
            value = o.parse(value)
        node = tree
        for name in o.path[:-1]:
            node = node.setdefault(name, {})
        node[o.path[-1]] = value
    return from_dict(cls, tree)


def setting_options(cls: type, options: Mapping[str, str]) -> dict[str, str]:
    """``{"Class.field": option}`` (the names :class:`~worldtree.infra.errors.SettingError` gives) of the
    settings of config ``cls`` that ``options`` (dotted path -> option) sets."""
    return {setting: options[path] for setting, path in setting_paths(cls).items() if path in options}


class GeneratedCommand:
    """A typer command function with generated options added to its own parameters.

    ``func`` declares the command's own parameters (arguments, output folder, ...) as usual, plus one parameter
    named ``param`` that receives what the generated options build. Subclasses say which options
    (:meth:`_generate`: ``(payload, [inspect.Parameter])``, called once, when typer first reads the signature)
    and what ``param`` gets from their values (:meth:`_collect`). Typer reads the command's parameters from
    ``__signature__`` and their types from ``__annotations__``; both are built here.
    """

    def __init__(self, func: Callable[..., Any], param: str) -> None:
        self.func, self.param = func, param
        self.__name__, self.__qualname__ = func.__name__, func.__qualname__
        self.__module__, self.__doc__ = func.__module__, func.__doc__

    def _generate(self) -> tuple[Any, list[inspect.Parameter]]:
        raise NotImplementedError

    def _collect(self, payload: Any, values: dict[str, Any]) -> Any:
        raise NotImplementedError

    def _options(self, payload: Any) -> Mapping[str, str]:
        """``{"Class.field": option}`` of the settings the generated options set (:func:`setting_options`):
        a :class:`~worldtree.infra.errors.SettingError` about one of them names its option."""
        return {}

    @functools.cached_property
    def _resolved(self) -> tuple[Any, list[inspect.Parameter], list[inspect.Parameter]]:
        payload, generated = self._generate()
        own = [
            p for p in inspect.signature(self.func, eval_str=True).parameters.values() if p.name != self.param
        ]
        clash = {p.name for p in own} & {p.name for p in generated}
        if clash:
            raise TypeError(
                f"{self.__name__}: parameters named like generated options: {', '.join(sorted(clash))}"
            )
        return payload, generated, own

    @property
    def __signature__(self) -> inspect.Signature:
        _, generated, own = self._resolved
        return inspect.Signature([*(p.replace(kind=inspect.Parameter.KEYWORD_ONLY) for p in own), *generated])

    @property
    def __annotations__(
        self,
    ) -> dict[str, Any]:  # read by typing.get_type_hints (typer resolves types with it)
        return {p.name: p.annotation for p in self.__signature__.parameters.values()}

    def __call__(self, **values: Any) -> Any:
        payload, _, own = self._resolved
        with options_named(self._options(payload)):
            return self.func(
                **{p.name: values[p.name] for p in own}, **{self.param: self._collect(payload, values)}
            )


class ConfigCommand(GeneratedCommand):
    """A command whose options come from a config dataclass: ``load`` returns ``(config class, options)``; it
    is called only when typer builds the command line (when the app runs), so a module that only registers the
    command does not import the config's module (``nvls`` sets its OpenMP policy before torch is imported).
    ``config_param`` receives the built config."""

    def __init__(
        self,
        func: Callable[..., Any],
        load: Callable[[], tuple[type, list[ConfigOption]]],
        config_param: str = "cfg",
    ) -> None:
        super().__init__(func, config_param)
        self.load = load

    @property
    def options(self) -> list[ConfigOption]:
        return self._resolved[0][1]

    def _generate(self) -> tuple[Any, list[inspect.Parameter]]:
        import typer

        cls, options = self.load()
        params = [
            inspect.Parameter(o.param, inspect.Parameter.KEYWORD_ONLY,
                              default=typer.Option(o.default, *o.decls, help=o.help), annotation=o.type)
            for o in options
        ]  # fmt: skip
        return (cls, options), params

    def _collect(self, payload: Any, values: dict[str, Any]) -> Any:
        cls, options = payload
        return config_from(cls, options, values)

    def _options(self, payload: Any) -> Mapping[str, str]:
        cls, options = payload
        return setting_options(cls, {o.dotted: o.decls[0].split("/")[0] for o in options})
