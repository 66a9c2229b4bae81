"""One module per `pointgt` subcommand.

Each module defines ``NAME`` (the subcommand), ``HELP`` (one line), ``add_arguments(parser)`` and
``run(args) -> int``. `tools.cli` discovers them, so adding a command never edits a shared file.
Heavy imports (torch, bpy) belong inside ``run`` so that ``pointgt --help`` stays instant.
"""
