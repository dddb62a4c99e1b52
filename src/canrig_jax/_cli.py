"""Command-line options derived from option dataclasses (one declaration, no hand copies).

``add_dataclass_options(parser, Options)`` adds ``--field-name`` for every field of a frozen
dataclass (nested dataclass fields are flattened into the same namespace), typed from its
annotations: ``bool`` -> ``--x / --no-x``, ``tuple[int, int]`` -> two values,
``tuple[float, ...]`` -> one or more, ``T | None`` -> ``T`` with default None. ``from_args``
rebuilds the dataclass from the parsed namespace.
"""

import argparse
import dataclasses
import types
import typing
from collections.abc import Mapping, Sequence
from typing import TypeVar

T = TypeVar("T")


def _flag(name: str) -> str:
    return "--" + name.replace("_", "-")


def _argument(hint) -> dict:
    """argparse keywords for a field annotation."""
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin in (typing.Union, types.UnionType):
        inner = [a for a in args if a is not type(None)]
        if len(inner) != 1:
            raise TypeError(f"cannot derive a command-line option from {hint}")
        return _argument(inner[0])
    if hint is bool:
        return {"action": argparse.BooleanOptionalAction}
    if origin is tuple:
        if len(args) == 2 and args[1] is Ellipsis:
            return {"type": args[0], "nargs": "+"}
        if len(set(args)) != 1:
            raise TypeError(f"cannot derive a command-line option from {hint}")
        return {"type": args[0], "nargs": len(args)}
    if hint in (int, float, str):
        return {"type": hint}
    raise TypeError(f"cannot derive a command-line option from {hint}")


def _fields(cls) -> list[tuple[dataclasses.Field, object]]:
    hints = typing.get_type_hints(cls)
    return [(f, hints[f.name]) for f in dataclasses.fields(cls)]


def add_dataclass_options(
    parser: argparse.ArgumentParser,
    cls: type,
    *,
    aliases: Mapping[str, Sequence[str]] | None = None,
    defaults: Mapping[str, object] | None = None,
    choices: Mapping[str, Sequence] | None = None,
    help: Mapping[str, str] | None = None,
    exclude: Sequence[str] = (),
) -> None:
    """Add one option per field of ``cls`` (and of its nested dataclass fields).

    ``aliases`` maps a field name to extra flags (e.g. ``{"n_heads": ["--heads"]}``),
    ``defaults`` overrides a field's default on the command line, ``choices`` restricts
    values, ``help`` documents a field, ``exclude`` leaves fields out (they keep their
    dataclass default)."""
    aliases, defaults = aliases or {}, defaults or {}
    choices, help = choices or {}, help or {}
    for field, hint in _fields(cls):
        if field.name in exclude:
            continue
        if isinstance(hint, type) and dataclasses.is_dataclass(hint):
            add_dataclass_options(
                parser,
                hint,
                aliases=aliases,
                defaults=defaults,
                choices=choices,
                help=help,
                exclude=exclude,
            )
            continue
        default = defaults.get(field.name, field.default)
        if default is dataclasses.MISSING:
            default = field.default_factory()  # type: ignore[misc]
        keywords = _argument(hint)
        if field.name in choices:
            keywords["choices"] = tuple(choices[field.name])
        text = help.get(field.name, "")
        parser.add_argument(
            _flag(field.name),
            *aliases.get(field.name, ()),
            dest=field.name,
            default=default,
            help=f"{text} (default: %(default)s)".strip(),
            **keywords,
        )


def from_args(cls: type[T], args: argparse.Namespace | Mapping, **overrides) -> T:
    """``cls`` built from parsed options (nested dataclasses rebuilt from the same namespace);
    ``overrides`` replace values by field name (at any nesting level)."""
    values = dict(vars(args) if isinstance(args, argparse.Namespace) else args)
    values.update(overrides)
    kwargs = {}
    for field, hint in _fields(cls):
        if isinstance(hint, type) and dataclasses.is_dataclass(hint):
            kwargs[field.name] = from_args(hint, values)
        elif field.name in values:
            value = values[field.name]
            kwargs[field.name] = tuple(value) if isinstance(value, list) else value
    return cls(**kwargs)
