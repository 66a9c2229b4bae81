"""`pointgt package-addon`: build the Blender extension zip (add-on + vendored core), validated by Blender."""
from __future__ import annotations

NAME = "package-addon"
HELP = "build the installable Blender add-on zip (prints its path as the last line)"
ORDER = 90


def add_arguments(parser):
    parser.add_argument("--out", default="build/addon", help="folder for the zip (created if missing)")
    parser.add_argument("--legacy", action="store_true",
                        help="build a legacy add-on zip (top folder pointgt/) instead of an extension")


def run(args) -> int:
    from tools.package_addon import build_addon

    path = build_addon(args.out, legacy=args.legacy)
    print("validated with Blender's extension validator")
    print(path.resolve())
    return 0
