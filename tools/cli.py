"""`pointgt` command line: discovers the subcommands in `tools.commands`."""
from __future__ import annotations

import argparse
import importlib
import pkgutil
import sys

from tools import commands


class UserError(Exception):
    """An error caused by the user's input; printed as one clear line, no traceback."""


def _command_modules():
    mods = []
    for info in pkgutil.iter_modules(commands.__path__):
        if info.name.startswith("_"):
            continue
        mod = importlib.import_module(f"tools.commands.{info.name}")
        if hasattr(mod, "NAME") and hasattr(mod, "run"):
            mods.append(mod)
    return sorted(mods, key=lambda m: getattr(m, "ORDER", 100))


class _HelpFormatter(argparse.ArgumentDefaultsHelpFormatter):
    """Shows each option's default once: not for options whose help already names it (the config fields) nor
    for options without one."""

    def _get_help_string(self, action):
        help_ = action.help or ""
        if action.default is None or "(default:" in help_:
            return help_
        return super()._get_help_string(action)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="pointgt",
        description="PointGT for Blender: reconstruct, pose and paint neural point clouds.",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for mod in _command_modules():
        p = sub.add_parser(mod.NAME, help=mod.HELP, description=getattr(mod, "DESCRIPTION", mod.HELP),
                           formatter_class=_HelpFormatter)
        mod.add_arguments(p)
        p.set_defaults(_run=mod.run)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "_run", None):
        parser.print_help()
        return 2
    from core.util.errors import PointGTError

    try:
        return int(args._run(args) or 0)
    except (UserError, PointGTError) as exc:
        print(f"pointgt {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except MemoryError:
        print(f"pointgt {args.command}: error: out of memory; the inputs are too large for this machine (try "
              "--downscale with --train-scales off, a smaller --size or fewer points)", file=sys.stderr)
        return 2
    except KeyboardInterrupt as exc:
        # A command may say what its outputs hold now (e.g. fit interrupted between its two saves).
        print(f"pointgt {args.command}: interrupted{f'; {exc}' if str(exc) else ''}", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
