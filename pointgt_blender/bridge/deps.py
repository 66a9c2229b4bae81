"""Optional dependencies of the add-on (torch): detection, extra site-packages folders, the pip command.

No bpy here: the add-on registers and imports models without torch; only the neural features need it.
torch is installed on request into the add-on's own user folder with Blender's Python (`sys.executable`),
or found in an existing environment's site-packages that the user points to.
"""
from __future__ import annotations

import importlib
import os
import sys
import sysconfig
from dataclasses import dataclass
from pathlib import Path

TORCH_REQUIREMENT = "torch==2.13.0"
TORCH_CPU_INDEX = "https://download.pytorch.org/whl/cpu"


@dataclass
class TorchStatus:
    available: bool
    version: str = ""
    problem: str = ""  # why torch is unusable, phrased for the user

    @property
    def message(self) -> str:
        if self.available:
            return f"PyTorch {self.version} is available"
        return f"PyTorch is missing: {self.problem}"


_status: TorchStatus | None = None


def torch_status(refresh: bool = False) -> TorchStatus:
    """Try `import torch` once (cached; `refresh=True` tries again, e.g. after an install or a path change)."""
    global _status
    if _status is not None and not refresh:
        return _status
    importlib.invalidate_caches()
    try:
        import torch  # noqa: F401  (the import itself is the test)

        _status = TorchStatus(True, str(getattr(torch, "__version__", "?")))
    except Exception as exc:  # a broken install raises more than ImportError; never let it escape
        _status = TorchStatus(False, problem=f"{type(exc).__name__}: {exc}. Install it from the add-on "
                                             f"preferences (Install PyTorch) or point them to a site-packages folder")
    return _status


def forget_status() -> None:
    """The next torch_status() call tries the import again."""
    global _status
    _status = None


def add_site_dir(path: str | os.PathLike) -> bool:
    """Append `path` to sys.path if it exists and is not there yet; returns True when it was added."""
    path = os.path.abspath(os.fspath(path))
    if not os.path.isdir(path) or path in sys.path:
        return False
    sys.path.append(path)  # appended, so Blender's own modules (numpy) always win
    return True


def remove_site_dir(path: str | os.PathLike) -> None:
    path = os.path.abspath(os.fspath(path))
    while path in sys.path:
        sys.path.remove(path)


def check_site_packages(path: str | os.PathLike) -> str:
    """Problems with a user-chosen site-packages folder, as one message ('' when it looks usable): it must exist,
    hold torch, and torch's compiled core must be built for this Python (Blender 4.2-5.0 ship Python 3.11)."""
    p = Path(os.fspath(path)).expanduser()
    if not str(path).strip():
        return ""
    if not p.is_dir():
        return f"{p}: folder not found; choose the site-packages folder of an environment that has torch"
    if not (p / "torch" / "__init__.py").is_file():
        return f"{p}: no torch package in this folder; choose the folder that contains 'torch/'"
    tag = sysconfig.get_config_var("EXT_SUFFIX") or ""
    compiled = [c.name for c in (p / "torch").glob("_C.*") if c.suffix in (".so", ".pyd")]
    if compiled and not any(c.endswith(tag) for c in compiled):
        ver = f"{sys.version_info.major}.{sys.version_info.minor}"
        return (f"{p}: torch there was built for another Python ({', '.join(compiled)}); Blender runs Python {ver} "
                f"- use an environment made with Python {ver}")
    return ""


def pip_install_command(target: str | os.PathLike, requirements: tuple[str, ...] = (TORCH_REQUIREMENT,),
                        index_url: str | None = TORCH_CPU_INDEX, find_links: str | None = None,
                        python: str | None = None) -> list[str]:
    """The pip command that installs `requirements` into the folder `target` with Blender's Python.
    `find_links` (a local folder of wheels) with `index_url=None` installs offline."""
    cmd = [python or sys.executable, "-m", "pip", "install", "--disable-pip-version-check", "--no-input",
           "--upgrade", "--target", os.fspath(target)]
    if index_url:
        cmd += ["--index-url", index_url]
    else:
        cmd += ["--no-index"]
    if find_links:
        cmd += ["--find-links", find_links]
    return cmd + list(requirements)


def ensurepip_command(python: str | None = None) -> list[str]:
    """Blender's bundled Python may lack pip; this bootstraps it from the wheels that Python ships with."""
    return [python or sys.executable, "-m", "ensurepip", "--upgrade"]


def pip_available(python: str | None = None) -> bool:
    import subprocess

    proc = subprocess.run([python or sys.executable, "-m", "pip", "--version"], capture_output=True)
    return proc.returncode == 0


def tail(text: str, lines: int = 6) -> str:
    """The last lines of a process log: what the user needs to see when an install fails."""
    return "\n".join(text.strip().splitlines()[-lines:])
