"""Device selection: every entry point takes a `device` option; nothing hard-codes CUDA."""
from __future__ import annotations

import torch

from core.util.errors import InputError


def resolve_device(name: str | torch.device | None = "auto") -> torch.device:
    """'auto' -> cuda when available else cpu; 'cpu', 'cuda', 'cuda:1' as given (checked)."""
    if isinstance(name, torch.device):
        return name
    if name in (None, "", "auto"):
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        dev = torch.device(name)
    except (RuntimeError, TypeError) as exc:
        raise InputError(f"device {name!r} is not a device; use auto, cpu or cuda") from exc
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise InputError(f"device '{name}' requested but CUDA is not available here; use --device cpu")
    return dev


def check_device(name: str | None, flag: str = "--device") -> torch.device:
    """resolve_device for a command-line flag: the error names `flag` (checked before any work)."""
    try:
        return resolve_device(name)
    except InputError as exc:
        raise InputError(f"{flag}: {exc}") from exc
