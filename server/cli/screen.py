"""``srd screen FILE``: screen one FSN manifest (exit 0 accepted, 1 refused or held, 2
malformed; 130 interrupted)."""

from __future__ import annotations

import json
import os
import select
import stat
import sys
from pathlib import Path
from typing import Any

import click
from pydantic import ValidationError
from rich.console import Console
from rich.markup import escape

from agents.manifest import ManifestError, name_problem, parse_manifest, parse_manifest_json
from screener import review, with_hold_reasons
from server.api.body import BodyRefusedError, parse_strict_json
from server.cli import loading
from server.cli.words import FiniteRange, json_failure
from server.config import Settings

ACCEPTED, REJECTED, MALFORMED = 0, 1, 2
"""Exit codes: accepted, not accepted (refused, or held for an inspector), unreadable or
malformed (the file, or a setting it is read and screened under)."""
WAKE_S = 0.25
"""How often a read of a pipe or a terminal that waits for its writer wakes (``_read_waiting``)."""
READ_UNDER = {"max_body_bytes": "SRD_MAX_BODY_BYTES", "screener_secret": "SRD_SCREENER_SECRET"}
"""The server's settings ``srd screen`` follows: the largest body ``POST /submit`` takes, and
the secret the screener draws its populations from (``screener.secret.SECRET_VARIABLE``)."""


def _emit(obj: dict[str, Any]) -> None:
    sys.stdout.write(json.dumps(obj) + "\n")


def _malformed(errors: list[dict[str, str]], json_output: bool) -> SystemExit:
    err = Console(stderr=True, soft_wrap=True)
    for e in errors:
        err.print(f"[red]error:[/red] {escape(_said(e))}", highlight=False)
    if json_output:
        first = errors[0] if errors else {"path": "$", "message": "malformed"}
        error = _said(first)
        _emit({"accepted": False, "reasons": [], "errors": errors, "error": error})
    return SystemExit(MALFORMED)


def _said(error: dict[str, str]) -> str:
    """An error as a line: ``path: message``, or the message alone for the whole file (``$``)."""
    path = error["path"]
    return error["message"] if path == "$" else f"{path}: {error['message']}"


def _settings(json_output: bool) -> Settings:
    """The settings of ``READ_UNDER`` from the environment, checked by their ``Settings`` fields
    as ``srd serve`` checks them (a secret ``srd serve`` refuses is refused here too); the other
    settings keep their defaults (the screener reads no secret file: only the variable)."""
    settings = Settings.model_construct()
    for field, variable in READ_UNDER.items():
        value = os.environ.get(variable, "")
        if not value:  # unset or empty: the default, as for the server (env_ignore_empty)
            continue
        try:  # bytes the environment could not decode stand as U+FFFD, one character each: the
            # screener hashes them as they are (screener.secret.secret_bytes)
            Settings.__pydantic_validator__.validate_assignment(settings, field, _text(value))
        except ValidationError as exc:
            shown = "" if field == "screener_secret" else f"={_text(value)}"
            said = str(exc.errors()[0]["msg"]).removeprefix("Value error, ")  # its own words
            problem = f"{variable}{shown}: {said}"
            Console(stderr=True, highlight=False, soft_wrap=True).print(
                f"[red]error:[/red] {escape(problem)}"
            )
            if json_output:
                json_failure(problem)
            raise SystemExit(MALFORMED) from None
    return settings


def _text(value: str) -> str:
    """A variable's value with the bytes the environment could not decode as U+FFFD."""
    try:
        return value.encode("utf-8", "surrogateescape").decode("utf-8", "replace")
    except UnicodeEncodeError:  # a surrogate no undecodable byte gives (not from os.environ)
        return value.encode("utf-8", "replace").decode("utf-8")


def _read(file: Path, limit: int) -> bytes:
    """The file's bytes; ``OSError`` if it cannot be read, ``ValueError`` if it holds more than
    ``limit`` (read no further: ``/dev/zero`` never ends)."""
    with file.open("rb") as stream:
        if stat.S_ISREG(os.fstat(stream.fileno()).st_mode):
            text = stream.read(limit + 1)
        else:  # a pipe or a terminal: its writer may keep us waiting
            text = _read_waiting(stream.fileno(), limit + 1)
    if len(text) > limit:
        raise ValueError(
            f"{file}: larger than {limit} bytes, the most POST /submit takes (SRD_MAX_BODY_BYTES)"
        )
    return text


def _read_waiting(fd: int, most: int) -> bytes:
    """Up to ``most`` bytes of a file that may keep us waiting, waking every ``WAKE_S``.

    Python runs a signal's handler between bytecodes: a Ctrl-C or SIGTERM that lands after the
    last such point and before a blocking ``read()`` would wait for the writer (for ever, if it
    waits for us to stop); a wait that wakes runs the handler within ``WAKE_S``."""
    poller = select.poll()
    poller.register(fd, select.POLLIN)
    chunks: list[bytes] = []
    size = 0
    while size < most:
        if not poller.poll(WAKE_S * 1000):
            continue
        chunk = os.read(fd, most - size)
        if not chunk:  # the writer closed its end
            break
        chunks.append(chunk)
        size += len(chunk)
    return b"".join(chunks)


def _json_errors(text: bytes) -> list[dict[str, str]]:
    """What the manifest parser says of text that is not JSON."""
    try:
        parse_manifest_json(text)
    except ManifestError as exc:
        return exc.errors
    return [{"path": "$", "message": "the file is not JSON"}]


@click.command("screen")
@click.argument("file", type=click.Path())
@click.option(
    "--json", "json_output", is_flag=True, help="Print exactly one JSON object on stdout."
)
@click.option(
    "--margin",
    type=FiniteRange(0, 1),
    default=Settings.model_fields["review_margin"].default,
    show_default=True,
    help="The server's review margin (SRD_REVIEW_MARGIN), in price: 'status' says whether a "
    "server with it would accept, refuse or hold the model for an inspector.",
)
def command(file: str, json_output: bool, margin: float) -> None:
    """Screen a Fish Sale Negotiator manifest: semantic rules on its named weights and
    behavioural probes, and the answer POST /submit would give: accepted, refused, or held
    for an inspector (within --margin of a bar, or by a bar that holds rather than refuses).
    Exit 0 accepted, 1 not accepted (refused or held: "accepted" is true only when accepted,
    as at /submit), 2 unreadable or malformed (read as POST /submit reads it: a key given
    twice, NaN or a byte-order mark is malformed). A file larger than SRD_MAX_BODY_BYTES is
    refused as the server refuses it; SRD_SCREENER_SECRET, if set, must be one srd serve
    takes. Exit 130 when interrupted (Ctrl-C)."""
    settings = _settings(json_output)
    if not file:  # Path("") would read the working folder, "."
        raise _malformed([{"path": "$", "message": "cannot read '': no file named"}], json_output)
    try:
        text = _read(Path(file), settings.max_body_bytes)
    except OSError as exc:
        raise _malformed([{"path": "$", "message": f"cannot read {file}: {exc.strerror}"}],
                         json_output) from exc  # fmt: skip
    except ValueError as exc:
        raise _malformed([{"path": "$", "message": str(exc)}], json_output) from exc
    try:  # read as strictly as POST /submit reads a body: a key twice, NaN, a BOM, depth
        manifest = parse_manifest(parse_strict_json(text))
    except BodyRefusedError as exc:
        if exc.kind == "not_json":  # the JSON parser's own words, with where it stopped
            errors = _json_errors(text)
        else:
            path = ".".join(str(part) for part in exc.loc[1:]) or "$"  # loc: ("body", ...)
            message = exc.msg.replace("the body", "the file", 1)
            errors = [{"path": path, "message": message}]
        raise _malformed(errors, json_output) from exc
    except ManifestError as exc:
        raise _malformed(exc.errors, json_output) from exc
    problem = name_problem(manifest.participant)  # as POST /submit refuses it
    if problem is not None:
        raise _malformed([{"path": "participant", "message": problem}], json_output)
    # torch and the screener's probes load only now: help, a usage error and a file that is no
    # manifest are answered without them (2 s sooner)
    with loading():
        import torch

        from screener import screen as screen_manifest
    torch.set_num_threads(1)  # the screener's tensors are tiny: more threads only contend
    verdict = screen_manifest(manifest)
    status = review(verdict, margin)
    screener_accepted = verdict.accepted
    verdict = with_hold_reasons(verdict, margin)
    accepted = status == "accepted"  # as /submit answers it: a held model is not accepted
    if json_output:
        _emit(
            {
                **verdict.to_dict(),
                "accepted": accepted,
                "status": status,
                "screener_accepted": screener_accepted,
            }
        )
    else:
        out = Console(highlight=False, soft_wrap=True)
        if status == "held":
            why = (
                "its reason below"
                if any(e.inspected() for e in verdict.evidence)
                else f"within {margin:g} of a bar"
            )
            word = f"[yellow]held[/yellow] (a server would hold it for an inspector: {why})"
        else:
            word = "[green]accepted[/green]" if accepted else "[red]rejected[/red]"
        out.print(f"{escape(manifest.participant)}: {word}")
        for reason in verdict.reasons:
            out.print(f"  [bold]{reason.neuron}[/bold] ({reason.rule}): {escape(reason.message)}")
    raise SystemExit(ACCEPTED if accepted else REJECTED)
