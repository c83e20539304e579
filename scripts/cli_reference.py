"""Write the command-line reference page, ``docs/cli.md``, from the real parser.

    python3 scripts/cli_reference.py            # rewrite docs/cli.md
    python3 scripts/cli_reference.py --check    # exit 1 if docs/cli.md differs from the parser

Every subcommand of ``hybridslam`` (``hybridslam.cli.build_parser``) gets a section with its
one-line description, a synopsis and a table of its arguments (names, value, default, help text),
and a last section lists every estimator option (``make_estimator`` keywords, read off the estimator
classes' fields), so the page cannot drift from the options that exist: ``tests/test_docs_blocks.py``
runs the check.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

PAGE = Path(__file__).resolve().parent.parent / "docs" / "cli.md"

HEADER = """# Command-line reference

Generated from the parser by `python3 scripts/cli_reference.py` (the test suite checks that this
page matches it). `hybridslam COMMAND --help` prints the same. Every command ends with exit status
2 and one line naming the field or option on bad input.

"""


def _subparsers(parser: argparse.ArgumentParser) -> dict[str, tuple[str, argparse.ArgumentParser]]:
    """The subcommands of a parser with their one-line help, in the order they were added."""
    out: dict[str, tuple[str, argparse.ArgumentParser]] = {}
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            helps = {a.dest: a.help or "" for a in action._choices_actions}
            for name, sub in action.choices.items():
                out[name] = (helps.get(name, ""), sub)
    return out


def _cell(text: object) -> str:
    return " ".join(str(text).split()).replace("|", "\\|").replace("<", "&lt;").replace(">", "&gt;")


def _value(action: argparse.Action) -> str:
    if action.nargs == 0:
        return ""
    if action.choices is not None and not isinstance(action, argparse._SubParsersAction):
        return "{" + ",".join(str(c) for c in action.choices) + "}"
    name = action.metavar or action.dest.upper()
    return f"[{name}]" if action.nargs == "?" else str(name)


def _section(prog: str, summary: str, parser: argparse.ArgumentParser, level: int) -> list[str]:
    subs = _subparsers(parser)
    positionals = [a for a in parser._actions if not a.option_strings and not isinstance(a, argparse._SubParsersAction)]
    options = [a for a in parser._actions if a.option_strings and not isinstance(a, argparse._HelpAction)]
    required = [a for a in options if a.required]
    synopsis = [prog] + [f"{a.option_strings[0]} {_value(a)}" for a in required]
    synopsis += ["[options]"] if len(options) > len(required) else []
    synopsis += [(a.metavar or a.dest).upper() for a in positionals]
    synopsis += ["{" + ",".join(subs) + "} ..."] if subs else []
    lines = [f"{'#' * level} `{prog}`", ""]
    if summary:
        lines += [_cell(summary)[:1].upper() + _cell(summary)[1:] + ".", ""]
    lines += ["```text", " ".join(synopsis), "```", ""]
    rows = positionals + options
    if rows:
        lines += ["| argument | value | default | what it does |", "|---|---|---|---|"]
        for a in rows:
            names = ", ".join(f"`{o}`" for o in a.option_strings) or f"`{(a.metavar or a.dest).upper()}`"
            unset = a.nargs == 0 or a.default is None or a.default is False or a.default == argparse.SUPPRESS
            default = "" if unset or a.required else f"`{a.default}`"
            value = _value(a)
            lines.append(f"| {names} | {f'`{value}`' if value else ''} | {default} | {_cell(a.help or '')} |")
        lines.append("")
    for name, (summary_, sub) in subs.items():
        lines += _section(f"{prog} {name}", summary_, sub, level + 1)
    return lines


def _estimator_options() -> list[str]:
    """Every estimator option (``make_estimator`` keywords), read off the registered estimators' fields."""
    from hybridslam.estimators.options import option_help
    from hybridslam.estimators.registry import ESTIMATORS, estimator_options

    lines = ["## Estimator options", "",
             "Every option of every estimator, read off the estimator classes' fields "
             "(`hybridslam/estimators/options.py`): `hs.make_estimator(name, **options)` takes them by name, "
             "the commands above the ones with a flag. An option an estimator has no use for is an error "
             "naming it.", "",
             "| option | flag | what it does |", "|---|---|---|"]
    for name, option in estimator_options().items():
        flag = f"`{option.flag}`" if option.command_line else ""
        lines.append(f"| `{name}` | {flag} | {_cell(option_help(option, ESTIMATORS))} |")
    return lines + [""]


def render() -> str:
    from hybridslam.cli import build_parser

    parser = build_parser()
    lines = [HEADER.rstrip("\n"), ""]
    for name, (summary, sub) in _subparsers(parser).items():
        lines += _section(f"hybridslam {name}", summary, sub, 2)
    lines += _estimator_options()
    return "\n".join(lines).rstrip("\n") + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--check", action="store_true", help="exit 1 if docs/cli.md differs from the parser")
    args = parser.parse_args(argv)
    text = render()
    if args.check:
        if PAGE.read_text(encoding="utf-8") != text:
            print(f"{PAGE} is out of date: run python3 scripts/cli_reference.py", file=sys.stderr)
            return 1
        return 0
    PAGE.write_text(text, encoding="utf-8")
    print(f"wrote {PAGE}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
