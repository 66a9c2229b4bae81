"""One module per `pointgt` subcommand.

Each module defines ``NAME`` (the subcommand), ``HELP`` (one line), ``add_arguments(parser)`` and
``run(args) -> int``. `tools.cli` discovers them, so adding a command never edits a shared file.
Heavy imports (torch, bpy) belong inside ``run`` so that ``pointgt --help`` stays instant.
"""


def add_model_and_data(p, model_help: str, data_help: str) -> None:
    """The positionals MODEL and DATA of a command that reads a model and its dataset, and --downscale (1-64,
    checked in `run`)."""
    p.add_argument("model", help=model_help)
    p.add_argument("data", help=data_help)
    p.add_argument("--downscale", type=int, default=1, help="integer image downscale factor (1-64)")
