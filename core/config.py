"""Typed config dataclasses: one per component, every field with a one-line help that becomes CLI help.

Declare fields with `opt(default, "help text")`; `add_to_parser` turns a dataclass into `--flags`, and
`from_args` builds the dataclass back from parsed arguments. Configs travel inside .pgt files as plain JSON
(`to_dict` / `from_dict`, unknown keys rejected) so a model remembers how it was made.

Limits live with the fields: `opt(32, "...", min=1, max=1024)` (inclusive bounds; `above=0` for a strict lower
bound), `choices=(...)`. `validate` is the one place they are checked: `from_args` (every command's flags) and
`from_dict` (settings read from a model file) call it, so a bad value is refused before any work, with the flag (or
the file's setting) named. Float fields must be finite; fields named `device` must name a torch device.
"""
from __future__ import annotations

import argparse
import dataclasses
import math
import re
from typing import Any, get_type_hints

from core.util.errors import InputError


def opt(default: Any, help: str, **kw):
    """A config field with a default and a one-line help string."""
    if isinstance(default, (list, dict, set)):
        return dataclasses.field(default_factory=lambda: type(default)(default), metadata={"help": help, **kw})
    return dataclasses.field(default=default, metadata={"help": help, **kw})


def _flag(prefix: str, name: str) -> str:
    return "--" + (f"{prefix}-" if prefix else "") + name.replace("_", "-")


def _limits(meta) -> str:
    """The declared range of a field for its --help line (' [>= 1]', ' [>= 0.0, <= 1.0]', ...)."""
    lo = meta.get("min", meta.get("above"))
    op = ">" if "above" in meta and "min" not in meta else ">="
    if lo is not None and "max" in meta:
        return f" [{op} {lo}, <= {meta['max']}]"
    if lo is not None:
        return f" [{op} {lo}]"
    return f" [<= {meta['max']}]" if "max" in meta else ""


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
        help_ = f.metadata.get("help", "") + _limits(f.metadata)
        if typ is bool:
            group.add_argument(_flag(prefix, f.name), dest=dest, action=argparse.BooleanOptionalAction,
                               default=None, help=f"{help_} (default: {default})")
        elif typ in (int, float, str):
            choices = f.metadata.get("choices")
            group.add_argument(_flag(prefix, f.name), dest=dest, type=typ, default=None, choices=choices,
                               help=f"{help_} (default: {default})")
        # other types (tuples, nested configs) are not exposed on the command line


_DEVICE = re.compile(r"^(auto|cpu|mps|cuda(:\d+)?)$")


def validate(cfg, prefix: str = "", names: dict[str, str] | None = None, flags: bool = True):
    """Check every field of the config `cfg` against its type and declared limits (`min`, `max`, `above`,
    `choices`); floats must be finite, `device` fields a torch device name. Raises InputError naming the flag
    (`--prefix-field`, or `names[field]`) or, with flags=False, the setting (`Class.field`). Returns cfg."""
    cls = type(cfg)
    hints = get_type_hints(cls)
    for f in dataclasses.fields(cls):
        val, typ, meta = getattr(cfg, f.name), hints[f.name], f.metadata
        if names and f.name in names:
            name = names[f.name]
        else:
            name = _flag(prefix, f.name) if flags else f"{cls.__name__}.{f.name}"
        if typ in (int, float, str, bool):
            ok = isinstance(val, typ) or (typ is float and isinstance(val, int))
            if not ok or (typ is not bool and isinstance(val, bool)):
                raise InputError(f"{name}: expected {'a number' if typ is float else typ.__name__}, got {val!r}")
        if typ is float and not math.isfinite(val):
            raise InputError(f"{name} must be a finite number, got {val!r}")
        if "min" in meta and val < meta["min"]:
            raise InputError(f"{name} must be at least {meta['min']}, got {val!r}")
        if "above" in meta and val <= meta["above"]:
            raise InputError(f"{name} must be greater than {meta['above']}, got {val!r}")
        if "max" in meta and val > meta["max"]:
            raise InputError(f"{name} must be at most {meta['max']}, got {val!r}")
        if meta.get("choices") is not None and val not in meta["choices"]:
            raise InputError(f"{name} must be one of {', '.join(map(str, meta['choices']))}, got {val!r}")
        if f.name == "device" and typ is str and not _DEVICE.match(val):
            raise InputError(f"{name} must be auto, cpu or cuda (cuda:N), got {val!r}")
    return cfg


def check_flag(value, flag: str, min=None, max=None):
    """A command's own numeric flag (one that belongs to no config), checked like a config field: finite and
    within [min, max]. Returns the value; raises InputError naming the flag."""
    if value is None:
        return value
    if isinstance(value, float) and not math.isfinite(value):
        raise InputError(f"{flag} must be a finite number, got {value!r}")
    if min is not None and value < min:
        raise InputError(f"{flag} must be at least {min}, got {value!r}")
    if max is not None and value > max:
        raise InputError(f"{flag} must be at most {max}, got {value!r}")
    return value


def from_args(cls, args: argparse.Namespace, prefix: str = "", base=None, names: dict[str, str] | None = None):
    """Build `cls` from parsed args, starting from `base` (or the defaults); unset flags keep their values.
    The result is validated (`validate`): a bad value raises InputError naming its flag."""
    obj = base if base is not None else cls()
    changes = {}
    for f in dataclasses.fields(cls):
        dest = (f"{prefix}_" if prefix else "") + f.name
        val = getattr(args, dest, None)
        if val is not None:
            changes[f.name] = val
    return validate(dataclasses.replace(obj, **changes), prefix, names)


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
    return validate(cls(**kwargs), flags=False)
