"""mkdocs hook: the command-line reference, generated at build time from the ``canrig`` parser.

``docs/cli.md`` holds the prose; the line ``<!-- canrig-cli-reference -->`` is replaced by the
help text of ``canrig`` and of every subcommand, formatted by argparse itself, so the page
cannot drift from the options the command accepts.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import os

MARKER = "<!-- canrig-cli-reference -->"
MODULE = "canrig_jax._commands"
WIDTH = "100"  # argparse wraps to $COLUMNS


def find_parser() -> argparse.ArgumentParser:
    """The ``canrig`` parser: ``build_parser()`` of the command module, or else the one
    function there whose name mentions a parser and that returns an ``ArgumentParser``."""
    module = importlib.import_module(MODULE)
    candidates = [getattr(module, "build_parser", None)]
    candidates += [
        getattr(module, name)
        for name in sorted(vars(module))
        if "parser" in name.lower() and name != "build_parser"
    ]
    for candidate in candidates:
        if not callable(candidate) or isinstance(candidate, type):
            continue
        try:
            parser = candidate()
        except TypeError:  # needs arguments: not a parser factory
            continue
        if isinstance(parser, argparse.ArgumentParser):
            return parser
    raise RuntimeError(f"{MODULE}: no function building the canrig ArgumentParser found")


def subcommands(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    """Subcommand name -> its parser, in the order they were added."""
    for action in parser._actions:  # argparse keeps no public list of subparsers
        if isinstance(action, argparse._SubParsersAction):
            return dict(action.choices)
    return {}


@contextlib.contextmanager
def _plain_help(width: str):
    """argparse's help wrapped at ``width`` columns and without colour (Python 3.14+)."""
    settings = {"COLUMNS": width, "NO_COLOR": "1"}
    previous = {name: os.environ.get(name) for name in settings}
    os.environ.update(settings)
    try:
        yield
    finally:
        for name, value in previous.items():
            if value is None:
                os.environ.pop(name, None)
            else:
                os.environ[name] = value


def _help(parser: argparse.ArgumentParser) -> str:
    text = parser.format_help().rstrip()
    return "```text\n" + text + "\n```\n"


def cli_markdown() -> str:
    """Markdown of ``canrig --help`` and each ``canrig SUBCOMMAND --help``."""
    with _plain_help(WIDTH):
        parser = find_parser()
        parts = ["## `canrig`\n", _help(parser)]
        for name, sub in subcommands(parser).items():
            parts += [f"## `canrig {name}`\n", _help(sub)]
    return "\n".join(parts)


def on_page_markdown(markdown: str, page, config, files) -> str:
    if MARKER not in markdown:
        return markdown
    return markdown.replace(MARKER, cli_markdown())
