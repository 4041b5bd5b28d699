"""The command reference (docs/reference/commands.md), generated from the parsers that run:
every command and subcommand of ``hil`` with its description, its usage and every argument
with its help, in the order ``hil --help`` gives them. ``python -m hil.cli.command_reference``
prints it; ``make docs`` writes it; a test holds the committed page to it, so it cannot drift.
"""

from __future__ import annotations

import argparse
from collections.abc import Iterator

#: the width the usage lines are wrapped at (not the terminal's: the page is the same anywhere)
WIDTH = 100

INTRO = """\
# Commands and flags

Generated from the command line's own parsers (`python -m hil.cli.command_reference`, `make
docs`): every command, its usage and every argument with its help, as `hil COMMAND --help`
prints them (every command also takes `-h`, `--help`). Do not edit by hand. The guides say
what the commands are for ([the command line](../guides/command-line.md)); the keys a flag
sets in a config file are in [the configuration reference](../CONFIGURATION.md).
"""


def subcommands(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    """The subcommands of ``parser`` by name (aliases left out), in their order."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            seen: dict[int, str] = {}
            for name, sub in action.choices.items():
                seen.setdefault(id(sub), name)
            return {name: action.choices[name] for name in seen.values()}
    return {}


def walk(parser: argparse.ArgumentParser) -> Iterator[argparse.ArgumentParser]:
    """``parser`` and every parser under it, depth first, in ``--help`` order."""
    yield parser
    for sub in subcommands(parser).values():
        yield from walk(sub)


def documented(parser: argparse.ArgumentParser) -> list[argparse.Action]:
    """The arguments of ``parser`` a user sees: not the subcommand choice, not a hidden one,
    not ``--help`` (every command has it)."""
    return [action for action in parser._actions
            if not isinstance(action, argparse._SubParsersAction | argparse._HelpAction)
            and action.help is not argparse.SUPPRESS]


def _formatter(parser: argparse.ArgumentParser) -> argparse.HelpFormatter:
    return parser.formatter_class(prog=parser.prog, width=WIDTH)  # type: ignore[call-arg]


def usage(parser: argparse.ArgumentParser) -> str:
    formatter = _formatter(parser)
    formatter.add_usage(parser.usage, parser._actions, parser._mutually_exclusive_groups)
    return formatter.format_help().strip()


def help_text(parser: argparse.ArgumentParser, action: argparse.Action) -> str:
    """An argument's help as ``--help`` prints it (``%(default)s`` and the like expanded)."""
    if not action.help:
        return ""
    return " ".join(_formatter(parser)._expand_help(action).split())


def invocation(action: argparse.Action) -> str:
    """``--umax MA, -u MA`` or ``URL``: how the argument is written."""
    if not action.option_strings:
        return str(action.metavar or action.dest)
    if action.nargs == 0:
        return ", ".join(action.option_strings)
    metavar = action.metavar or action.dest.upper()
    if isinstance(metavar, tuple):
        metavar = " ".join(metavar)
    return ", ".join(f"{name} {metavar}" for name in action.option_strings)


def _cell(text: str) -> str:
    """``text`` as one Markdown table cell: its bars escaped, and ``][`` too (``[-END][:K=V]``
    would read as a reference link)."""
    return text.replace("|", "\\|").replace("\n", " ").replace("][", "]\\[")


def _command_help(parent: argparse.ArgumentParser, name: str) -> str:
    for action in parent._actions:
        if isinstance(action, argparse._SubParsersAction):
            for choice in action._choices_actions:
                if choice.dest == name:
                    return choice.help or ""
    return ""


def section(parser: argparse.ArgumentParser) -> list[str]:
    """One command's part of the page."""
    level = "#" * min(parser.prog.count(" ") + 2, 6)
    lines = [f"{level} `{parser.prog}`", ""]
    if parser.description:
        lines += [" ".join(parser.description.split()), ""]
    lines += ["```text", usage(parser), "```", ""]
    subs = subcommands(parser)
    if subs:
        lines += ["| command | what it does |", "|---|---|"]
        lines += [f"| [`{sub.prog}`](#{anchor(sub.prog)}) | {_cell(_command_help(parser, name))} |"
                  for name, sub in subs.items()]
        lines.append("")
    arguments = documented(parser)
    if arguments:
        lines += ["| argument | what it does |", "|---|---|"]
        lines += [f"| `{_cell(invocation(a))}` | {_cell(help_text(parser, a))} |"
                  for a in arguments]
        lines.append("")
    if parser.epilog:
        lines += [" ".join(parser.epilog.split()), ""]
    return lines


def anchor(prog: str) -> str:
    """The heading anchor of a command's section (Markdown's toc: ``hil servo run`` ->
    ``hil-servo-run``)."""
    return prog.replace(" ", "-")


def reference() -> str:
    """docs/reference/commands.md."""
    from hil.cli.main import build_parser

    lines = [INTRO]
    for parser in walk(build_parser()):
        lines += section(parser)
    return "\n".join(lines).rstrip() + "\n"


if __name__ == "__main__":
    print(reference(), end="")
