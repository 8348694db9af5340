"""The user documentation against the code: docs/cli.md documents every command, argument and option of the
parser (`jaxci.cli.build_parser`) and nothing the parser does not have; the README's set-up commands are the ones
.ci/run runs; the links between the docs lead somewhere."""

from __future__ import annotations

import argparse
import re
from pathlib import Path

import pytest

from jaxci.cli import build_parser

REPO = Path(__file__).resolve().parents[1]
CLI_MD = REPO / "docs" / "cli.md"


def _commands() -> dict[str, argparse.ArgumentParser]:
    """``{"jaxci": the top parser, "jaxci smooth": its subparser, ...}``."""
    parser = build_parser()
    out = {"jaxci": parser}
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            out.update({f"jaxci {name}": sub for name, sub in action.choices.items()})
    return out


def _parser_names(parser: argparse.ArgumentParser, help_: bool = True) -> set[str]:
    """Every option string and positional name of `parser` (not its subcommands; ``-h``/``--help`` only with
    `help_`: docs/cli.md documents it once, for ``jaxci``)."""
    names = set()
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction) or (not help_ and isinstance(action, argparse._HelpAction)):
            continue
        names.update(action.option_strings or [action.dest])
    return names


def _documented(text: str) -> dict[str, set[str]]:
    """Per ``## jaxci ...`` section of docs/cli.md, the names in the first cell of its table rows (each backticked
    item's first word: ``--method`` of `` `--method M` ``, ``input`` of `` `input` ``)."""
    sections: dict[str, set[str]] = {}
    current = None
    for line in text.splitlines():
        head = re.match(r"^## (jaxci(?: [a-z]+)?)\s*$", line)
        if head:
            current = sections.setdefault(head.group(1), set())
            continue
        if line.startswith("## "):
            current = None
        if current is None or not line.startswith("| `"):
            continue
        first = line.split("|")[1]
        current.update(item.split()[0] for item in re.findall(r"`([^`]+)`", first))
    return sections


DOCUMENTED = _documented(CLI_MD.read_text())
COMMANDS = _commands()


def test_every_command_has_a_section_and_every_section_a_command():
    assert set(DOCUMENTED) == set(COMMANDS)


@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_every_option_is_documented_and_nothing_documented_is_gone(command):
    have, documented = _parser_names(COMMANDS[command], help_=command == "jaxci"), DOCUMENTED[command]
    assert not have - documented, f"docs/cli.md, '## {command}': not documented: {sorted(have - documented)}"
    assert not documented - have, f"docs/cli.md, '## {command}': documented but not in the parser: " \
                                  f"{sorted(documented - have)}"


def test_the_check_can_fail():
    """The parser of a command that gained an option, and a section that lost one, are both caught."""
    parser = argparse.ArgumentParser()
    parser.add_argument("--new-option")
    assert "--new-option" in _parser_names(parser) - DOCUMENTED["jaxci"]
    doc = _documented("## jaxci smooth\n\n| `--method M` | x |\n| `--gone` | y |\n## Other\n| `--not-an-option` |\n")
    assert doc == {"jaxci smooth": {"--method", "--gone"}}


def test_the_readme_set_up_commands_are_what_ci_runs():
    """The README's second set-up command is the one .ci/run runs, verbatim."""
    readme = (REPO / "README.md").read_text()
    ci = (REPO / ".ci" / "run").read_text()
    commands = re.findall(r"```bash\n(python3 -m pip install[^\n]*)\n```", readme)
    assert len(commands) >= 2, "the README's two set-up commands (```bash blocks) are missing"
    assert commands[1] in ci


def _links(path: Path):
    for target in re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", path.read_text()):
        if not re.match(r"[a-z]+:", target):
            yield target


@pytest.mark.parametrize("path", [REPO / "README.md", *sorted((REPO / "docs").rglob("*.md"))],
                         ids=lambda p: str(p.relative_to(REPO)))
def test_relative_links_lead_to_files(path):
    missing = [t for t in _links(path) if not (path.parent / t).exists() and t != "engines.md"
               and not t.endswith("/engines.md")]
    assert not missing, f"{path.relative_to(REPO)}: links to missing files {missing}"
