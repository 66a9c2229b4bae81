"""Typed config dataclasses: one per component, every field with a one-line help that becomes CLI help.

Declare fields with `opt(default, "help text")`; `add_to_parser` turns a dataclass into `--flags`, and
`from_args` builds the dataclass back from parsed arguments. Configs travel inside .pgt files as plain JSON
(`to_dict` / `from_dict`, unknown keys rejected) so a model remembers how it was made.
"""
from __future__ import annotations

import argparse
import dataclasses
from typing import Any, get_type_hints

from core.util.errors import InputError


def opt(default: Any, help: str, **kw):
    """A config field with a default and a one-line help string."""
    if isinstance(default, (list, dict, set)):
        return dataclasses.field(default_factory=lambda: type(default)(default), metadata={"help": help, **kw})
    return dataclasses.field(default=default, metadata={"help": help, **kw})


def _flag(prefix: str, name: str) -> str:
    return "--" + (f"{prefix}-" if prefix else "") + name.replace("_", "-")


def add_to_parser(parser: argparse.ArgumentParser, cls, prefix: str = "", skip: tuple[str, ...] = ()) -> None:
    """Add one `--field` option per dataclass field (bools get `--x/--no-x`)."""
    hints = get_type_hints(cls)
    group = parser.add_argument_group(cls.__name__, (cls.__doc__ or "").strip().splitlines()[0] if cls.__doc__ else None)
    for f in dataclasses.fields(cls):
        if f.name in skip or f.metadata.get("cli") is False:
            continue
        typ = hints[f.name]
        default = f.default if f.default is not dataclasses.MISSING else f.default_factory()
        dest = (f"{prefix}_" if prefix else "") + f.name
        help_ = f.metadata.get("help", "")
        if typ is bool:
            group.add_argument(_flag(prefix, f.name), dest=dest, action=argparse.BooleanOptionalAction,
                               default=None, help=f"{help_} (default: {default})")
        elif typ in (int, float, str):
            choices = f.metadata.get("choices")
            group.add_argument(_flag(prefix, f.name), dest=dest, type=typ, default=None, choices=choices,
                               help=f"{help_} (default: {default})")
        # other types (tuples, nested configs) are not exposed on the command line


def from_args(cls, args: argparse.Namespace, prefix: str = "", base=None):
    """Build `cls` from parsed args, starting from `base` (or the defaults); unset flags keep their values."""
    obj = base if base is not None else cls()
    changes = {}
    for f in dataclasses.fields(cls):
        dest = (f"{prefix}_" if prefix else "") + f.name
        val = getattr(args, dest, None)
        if val is not None:
            changes[f.name] = val
    return dataclasses.replace(obj, **changes)


def to_dict(cfg) -> dict:
    return dataclasses.asdict(cfg)


def from_dict(cls, data: dict):
    """Rebuild a config from JSON data, rejecting unknown keys and wrong types with a clear message."""
    if not isinstance(data, dict):
        raise InputError(f"{cls.__name__}: expected an object, got {type(data).__name__}")
    hints = get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = set(data) - names
    if unknown:
        raise InputError(f"{cls.__name__}: unknown settings {sorted(unknown)}")
    kwargs = {}
    for key, val in data.items():
        typ = hints[key]
        if typ is float and isinstance(val, int) and not isinstance(val, bool):
            val = float(val)
        if typ in (int, float, str, bool) and not isinstance(val, typ):
            raise InputError(f"{cls.__name__}.{key}: expected {typ.__name__}, got {val!r}")
        if isinstance(val, list):
            val = tuple(val)
        kwargs[key] = val
    return cls(**kwargs)
