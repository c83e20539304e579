"""Every ``hybridslam`` command line the README and the documentation pages give parses with the real
command-line parser.

The README's commands are what users copy. A renamed or removed option would make them fail; this
test reads every ``hybridslam ...`` line of the README's ``bash`` blocks (continuation lines joined,
comments dropped; synopsis lines with ``[optional]`` parts are checked option by option) and hands
it to :func:`hybridslam.cli.build_parser`. Running them is the job of the CLI tests (``run``,
``simulate``, ``import``, ``sweep``, ``plot`` each run there on small inputs), since the README's
own are minutes-long studies.
"""

from __future__ import annotations

import re
import shlex

import pytest

from hybridslam.cli import build_parser

from .docblocks import all_blocks, commands


def _commands() -> list[str]:
    """Every ``hybridslam ...`` command of the README's and the documentation pages' bash blocks."""
    return list(dict.fromkeys(c for b in all_blocks("bash") for c in commands(b) if c.startswith("hybridslam ")))


def _concrete(line: str) -> list[str]:
    """A synopsis line's ``[--opt a|b]`` parts become ``--opt a`` (each alternative is a value)."""
    line = re.sub(r"\[([^\[\]]*)\]", lambda m: m.group(1).split("|")[0].replace("...", "").strip(), line)
    line = re.sub(r"(\S+)\|\S+", r"\1", line)
    return [t for t in shlex.split(line)[1:] if t != "..."]


COMMANDS = _commands()


def test_the_readme_documents_commands():
    assert len(COMMANDS) >= 8, COMMANDS
    assert any(c.startswith("hybridslam sweep -o runs/sweep") for c in COMMANDS)  # the main job


@pytest.mark.parametrize("line", COMMANDS)
def test_documented_command_parses(line):
    args = build_parser().parse_args(_concrete(line))
    assert callable(args.func)
