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
import types
import typing
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

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


def _optional_of(tp: Any) -> tuple[Any, bool]:
    """``X | None`` -> ``(X, True)``; ``X`` -> ``(X, False)``."""
    if typing.get_origin(tp) in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        if len(args) == 1 and len(typing.get_args(tp)) == 2:
            return args[0], True
    return tp, False


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
            base, _ = _optional_of(tp)
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
    return _construct(cls, tree)


def _construct(cls: type, tree: Mapping[str, Any]) -> Any:
    hints = typing.get_type_hints(cls)
    kwargs = {
        name: _construct(hints[name], value) if isinstance(value, dict) and dataclasses.is_dataclass(hints[name])
        else value
        for name, value in tree.items()
    }  # fmt: skip
    return cls(**kwargs)


class ConfigCommand:
    """A typer command function whose options come from a config dataclass.

    ``func`` declares the command's own parameters (arguments, output folder, ...) as usual, plus one parameter
    named ``config_param`` that receives the built config. ``load`` returns ``(config class, options)``; it is
    called only when typer builds the command line (when the app runs), so a module that only registers the
    command does not import the config's module (``nvls`` sets its OpenMP policy before torch is imported).
    """

    def __init__(
        self,
        func: Callable[..., Any],
        load: Callable[[], tuple[type, list[ConfigOption]]],
        config_param: str = "cfg",
    ) -> None:
        self.func = func
        self.load = load
        self.config_param = config_param
        self.__name__ = func.__name__
        self.__qualname__ = func.__qualname__
        self.__module__ = func.__module__
        self.__doc__ = func.__doc__

    @functools.cached_property
    def _resolved(self) -> tuple[type, list[ConfigOption], list[inspect.Parameter]]:
        cls, options = self.load()
        own = [
            p for p in inspect.signature(self.func, eval_str=True).parameters.values() if p.name != self.config_param
        ]  # fmt: skip
        clash = {p.name for p in own} & {o.param for o in options}
        if clash:
            raise TypeError(
                f"{self.__name__}: parameters named like config options: {', '.join(sorted(clash))}"
            )
        return cls, options, own

    @property
    def options(self) -> list[ConfigOption]:
        return self._resolved[1]

    @property
    def __signature__(self) -> inspect.Signature:
        import typer

        _, options, own = self._resolved
        generated = [
            inspect.Parameter(
                o.param,
                inspect.Parameter.KEYWORD_ONLY,
                default=typer.Option(o.default, *o.decls, help=o.help),
                annotation=o.type,
            )
            for o in options
        ]
        own = [p.replace(kind=inspect.Parameter.KEYWORD_ONLY) for p in own]
        return inspect.Signature([*own, *generated])

    @property
    def __annotations__(
        self,
    ) -> dict[str, Any]:  # read by typing.get_type_hints (typer resolves types with it)
        return {p.name: p.annotation for p in self.__signature__.parameters.values()}

    def __call__(self, **values: Any) -> Any:
        cls, options, own = self._resolved
        cfg = config_from(cls, options, values)
        return self.func(**{p.name: values[p.name] for p in own}, **{self.config_param: cfg})
