"""How the command line shows names and numbers to a person: help text without reStructuredText
markup, table headers in words, floats to three significant digits; and, under ``--json``, a
failure as the one JSON object on stdout."""

from __future__ import annotations

import json
import math
import re
import sys
from typing import Any

import click

SIGNIFICANT = 3
"""Significant digits of a float in a table or a card."""
HEADERS = {
    "rarity": "supply: fish on sale per patron",
    "n_fish": "fish on sale",
    "n_params": "parameters",
    "n_runs": "runs",
    "elapsed_s": "elapsed (s)",
}
"""Result fields whose header is not just their name in words."""
ACRONYMS = {"srd": "SRD", "lr": "learning rate"}
_LITERAL = re.compile(r"``(.+?)``|`([^`]+)`")


def plain(text: str) -> str:
    """Help text as a terminal shows it: ``x`` and `x` become x (the config docstrings are
    written for Sphinx and the code's readers)."""
    return _LITERAL.sub(lambda m: m.group(1) or m.group(2), text)


def header(name: str) -> str:
    """A result field as a column or row header: ``mean_price`` → ``mean price``."""
    if name in HEADERS:
        return HEADERS[name]
    return " ".join(ACRONYMS.get(word, word) for word in name.split("_"))


def rounded(value: float) -> str:
    """``value`` to three significant digits, trailing zeros dropped, without an exponent from
    0.001 up: 5.1913 → 5.19, 0.012345 → 0.0123, 1234.5 → 1230, 0.5 → 0.5, 2e-05 → 2e-05."""
    if not math.isfinite(value) or value == 0:
        return f"{value:g}"
    magnitude = math.floor(math.log10(abs(value)))
    if magnitude < -3:
        return f"{value:.{SIGNIFICANT}g}"
    decimals = SIGNIFICANT - 1 - magnitude
    text = f"{round(value, decimals):.{max(decimals, 0)}f}"
    return text.rstrip("0").rstrip(".") if "." in text else text


def json_failure(
    message: str,
    errors: list[dict[str, str]] | None = None,
    command: str | None = None,
    extra: dict[str, Any] | None = None,
) -> None:
    """A command that fails under ``--json`` still prints exactly one JSON object on stdout:
    ``{"error": message}``, with ``errors`` (``[{option, message}]``) when options were at
    fault, what it had made when stopped midway (``extra``: ``srd agents``'s models), and for
    ``srd screen`` its verdict's keys (``accepted`` false, no ``reasons``), as its malformed
    files answer. The person reads the same on stderr; the exit code is the command's."""
    obj: dict[str, Any] = {"accepted": False, "reasons": []} if command == "screen" else {}
    obj.update(extra or {})
    obj["error"] = message
    if errors is not None:
        obj["errors"] = errors
    sys.stdout.write(json.dumps(obj) + "\n")


class IntegerRange(click.IntRange):
    """``click.IntRange`` whose refusal of what is no integer says so ("'abc' is not a valid
    integer"; click's says "integer range", as if a range had been asked for)."""

    name = "integer"


class FiniteRange(click.FloatRange):
    """``click.FloatRange`` that also refuses ``nan`` and ``inf`` (a usage error naming the
    option, exit 2): click's own range lets NaN through, every comparison with it being
    false."""

    name = "finite float range"

    def convert(self, value: Any, param: click.Parameter | None, ctx: click.Context | None) -> Any:
        number = click.FLOAT.convert(value, param, ctx)
        if not math.isfinite(number):
            self.fail(f"{value!r} is not a finite number.", param, ctx)
        return super().convert(number, param, ctx)
