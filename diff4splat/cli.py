"""``diff4splat`` command line: it only dispatches. Each command is a module of :mod:`diff4splat.commands`
(``generate``, ``reconstruct``, ``export-onnx``, ``render``, ``view``) or a :data:`PLUGIN_GROUP` entry point
(``training``'s ``evaluate``, ``fit``) that registers its own flags. Bad input gets one line on stderr
(``diff4splat: error: …``), exit code 2 and no output folder.
"""
from __future__ import annotations

import argparse
import sys
from importlib.metadata import entry_points

from diff4splat.commands import export, generate, reconstruct, render, view
from diff4splat.utils.errors import run_cli

__all__ = ["main", "build_parser", "PLUGIN_GROUP"]

PLUGIN_GROUP = "diff4splat.commands"
"""Entry-point group of extra subcommands (``training``'s ``evaluate``): ``register(subparsers)`` adds a parser whose
defaults hold ``func(args) -> int``; it is loaded only when its command is chosen."""
COMMANDS = (generate, export, render, reconstruct, view)
"""The built-in commands, in the order ``diff4splat --help`` lists them."""


class CLIError(Exception):
    """A user error reported as one line with exit code 2."""


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> None:  # one line, exit 2 (argparse prints usage + message)
        raise CLIError(message)


def build_parser(load_command: str | None = None) -> argparse.ArgumentParser:
    """The ``diff4splat`` argument parser; :data:`PLUGIN_GROUP` commands get a placeholder subparser except
    ``load_command``, whose entry point is loaded. ValueError: ``load_command`` is not a registered entry point."""
    parser = _Parser(prog="diff4splat", description="One photograph + a camera path + a prompt → a 4D Gaussian scene.")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)
    for command in COMMANDS:
        command.register(sub)
    plugins = {ep.name: ep for ep in entry_points(group=PLUGIN_GROUP)}  # e.g. `evaluate`, from `training`
    if load_command is not None and load_command not in plugins:
        raise ValueError(f"load_command: {load_command!r} is not a {PLUGIN_GROUP} entry point "
                         f"(known: {sorted(plugins)})")
    for name, ep in plugins.items():
        if name == load_command:
            ep.load()(sub)
        else:  # placeholder: its arguments are left unparsed until the entry point is loaded
            placeholder = sub.add_parser(name, add_help=False, help=f"(from {ep.module}; `diff4splat {name} --help`)")
            placeholder.set_defaults(plugin=name)
    return parser


def main(argv: list[str] | None = None) -> int:
    """The ``diff4splat`` console script; returns the exit code: 0, 2 after an expected failure
    (:func:`diff4splat.utils.errors.run_cli`), 130 after Ctrl-C."""
    return run_cli("diff4splat", lambda: _main(argv), expected=(CLIError,))


def _main(argv: list[str] | None) -> int:
    parser = build_parser()
    args, unknown = parser.parse_known_args(argv)
    if getattr(args, "plugin", None) is not None:  # load that command's entry point, parse again
        args = build_parser(load_command=args.plugin).parse_args(argv)
    elif unknown:
        parser.error(f"unrecognized arguments: {' '.join(unknown)}")
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())
