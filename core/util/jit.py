"""Compiled loops: numba where it is installed (an optional dependency), the plain Python function elsewhere."""
from __future__ import annotations

try:
    import numba
except ImportError:  # pragma: no cover - exercised only where numba is missing
    numba = None


def njit(fn):
    """fn compiled by numba on first call (nogil; cached on disk where a cache location is writable, so later
    processes skip the compile, else compiled once per process); fn itself without numba."""
    if numba is None:
        return fn
    try:
        return numba.njit(cache=True, nogil=True)(fn)
    except RuntimeError:  # no writable cache location (read-only install): compile per process
        return numba.njit(cache=False, nogil=True)(fn)
