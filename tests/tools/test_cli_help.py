"""Every command's --help names each option's default at most once and never as 'None'."""
import re

from tools.cli import build_parser


def _subparsers(parser):
    for action in parser._actions:
        if getattr(action, "choices", None) and isinstance(action.choices, dict):
            yield from action.choices.items()


def test_help_shows_defaults_once():
    commands = dict(_subparsers(build_parser()))
    assert {"fit", "render", "demo"} <= set(commands)
    for name, sub in commands.items():
        text = sub.format_help()
        assert "(default: None)" not in text, name
        for action in sub._actions:
            help_ = sub._get_formatter()._expand_help(action) if action.help else ""
            assert len(re.findall(r"\(default:", help_)) <= 1, (name, action.dest, help_)
