"""The screener's page shows `srd screen` at work on files of this project: what it shows is
what the command prints today (its reasons, word for word, and its exit code)."""

from __future__ import annotations

import json
import re
import shlex
from pathlib import Path

import pytest
from click.testing import CliRunner

from server.cli import cli

ROOT = Path(__file__).resolve().parents[2]
PAGE = ROOT / "docs" / "screener.md"
EXIT = re.compile(r"\s+\((?:stderr, )?exit (\d)\)$")


def documented() -> list[tuple[str, list[str]]]:
    """Each ``$ srd screen FILE ...`` example on the page whose file is in the project, with
    the lines shown under it (up to the next blank line or the block's end)."""
    examples: list[tuple[str, list[str]]] = []
    lines = PAGE.read_text().splitlines()
    for i, line in enumerate(lines):
        if not line.startswith("$ srd screen "):
            continue
        command = line[2:].split("  #")[0].strip()
        if not (ROOT / shlex.split(command)[2]).is_file():
            continue  # a file the page makes up (mallory.json): shown, not run
        shown = []
        for after in lines[i + 1 :]:
            if not after.strip() or after.startswith("```"):
                break
            shown.append(after)
        examples.append((command, shown))
    return examples


EXAMPLES = documented()


def test_the_page_shows_examples_of_files_in_the_project() -> None:
    assert len(EXAMPLES) >= 5, EXAMPLES


@pytest.mark.parametrize(("command", "shown"), EXAMPLES, ids=[c for c, _ in EXAMPLES])
def test_a_documented_screen_prints_what_the_page_shows(command: str, shown: list[str]) -> None:
    words = shlex.split(command.split(" | ")[0])[1:]
    result = CliRunner().invoke(cli, words)
    (code,) = {int(m.group(1)) for line in shown if (m := EXIT.search(line))}
    assert result.exit_code == code, result.output
    expected = [EXIT.sub("", line).rstrip() for line in shown]
    if " | jq -c " in command:  # the page's jq program picks these fields
        answer = json.loads(result.stdout)
        picked = [answer["accepted"], answer["status"], answer["screener_accepted"]]
        picked += [reason["rule"] for reason in answer["reasons"]]
        assert expected == [json.dumps(picked, separators=(",", ":"))]
    else:
        assert result.stdout.splitlines() == expected
