"""Benchmark scripts (`python -m tools.bench.<name> --help`); results.md quotes their output.

What the scripts share: the parser from the script's docstring, the --threads / --json flags, a config's
flags (core.config) with its `threads` field applied, and running one `pointgt` command as a user would."""
from __future__ import annotations

import argparse
import subprocess
import time


def parser(doc: str) -> argparse.ArgumentParser:
    """A script's parser, described by the first line of its docstring `doc`."""
    return argparse.ArgumentParser(description=doc.splitlines()[0])


def add_scene(ap: argparse.ArgumentParser, every_help: str) -> None:
    """--scene (a folder made by `pointgt make-scene`, whose scene.blend holds the true mesh) and --every."""
    ap.add_argument("--scene", required=True, help="scene folder made by `pointgt make-scene` (scene.blend)")
    ap.add_argument("--every", type=int, default=2, help=every_help)


def add_samples(ap: argparse.ArgumentParser) -> None:
    """--samples: Cycles samples per pixel of the scenes a bench makes (0 = make-scene's default); pass it on with
    `samples_flag`."""
    ap.add_argument("--samples", type=int, default=0,
                    help="Cycles samples per pixel of the scenes it makes (0 = make-scene's default)")


def samples_flag(samples: int) -> list[str]:
    """The --samples flag of `add_samples` for a make-scene (or scene-making bench) command line: none for 0."""
    return ["--samples", str(samples)] if samples else []


def parse(ap: argparse.ArgumentParser, argv=None, threads: int = 1) -> argparse.Namespace:
    """Add --threads (default `threads`; 0 = torch's default) and --json, parse argv, apply --threads."""
    ap.add_argument("--threads", type=int, default=threads, help="torch threads (0 = torch's default)")
    ap.add_argument("--json", default=None, help="write the figures to this JSON file")
    args = ap.parse_args(argv)
    _set_threads(args.threads)
    return args


def write_json(path, figures) -> None:
    """Write `figures` (JSON-serialisable; numpy/torch scalars become floats) to `path` atomically, if a path
    is given (the scripts' --json, whose default is none)."""
    if not path:
        return
    import json

    from core.util.atomic import atomic_write_text

    atomic_write_text(path, json.dumps(figures, indent=1, default=float))


def parse_with_config(ap: argparse.ArgumentParser, cls, argv=None):
    """Add the flags of the config dataclass `cls`, parse argv, build (and validate) the config and apply its
    `threads` field (> 0) to torch. Returns (args, config)."""
    from core.config import add_to_parser, from_args

    add_to_parser(ap, cls)
    args = ap.parse_args(argv)
    cfg = from_args(cls, args)
    _set_threads(cfg.threads)
    return args, cfg


def _set_threads(threads: int) -> None:
    if threads > 0:
        import torch

        torch.set_num_threads(threads)


def run_command(cmd: list[str], log, check: bool = False) -> int:
    """Run `cmd` in its own process, logging it (`log`: a print-like function) and its wall time. check: a
    failure stops the script with the command and the end of its output; otherwise the last lines of its output
    are logged and its exit code returned."""
    log("$ " + " ".join(cmd))
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True)
    lines = (proc.stdout + proc.stderr).strip().splitlines()
    if check:
        if proc.returncode != 0:
            raise SystemExit(f"command failed (exit {proc.returncode}): {' '.join(cmd)}\n" + "\n".join(lines[-5:]))
        log(f"  done in {time.perf_counter() - t0:.0f} s")
        return 0
    for line in lines[-3:]:
        log("  " + line)
    log(f"  exit {proc.returncode} after {time.perf_counter() - t0:.0f} s")
    return proc.returncode
