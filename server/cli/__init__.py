"""The ``srd`` command line.

Every command is imported only when it runs, so ``srd --help`` answers without importing torch
or any simulation: the experiment commands (one per kind of ``studies.registry``) are generated
from their config dataclasses by ``server.cli.experiment``; ``serve``, ``screen``, ``agents`` and
``watch`` are written by hand in their own modules, each exposing ``command``.
"""

from __future__ import annotations

import contextlib
import gc
import importlib
import os
import signal
import sys
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from typing import Any

import click

from server.cli.words import json_failure, plain
from studies.registry import KINDS

HELP = "Self Reward Design: fish sale auction service, screener and the paper's experiments."
HAND_WRITTEN = {
    "serve": ("server.cli.serve", "Run the HTTP API (uvicorn) on the configured database."),
    "screen": ("server.cli.screen", "Screen one Fish Sale Negotiator manifest."),
    "agents": ("server.cli.agents", "Run remote agents that submit and fine-tune over HTTP."),
    "healthcheck": ("server.cli.healthcheck", "Exit 0 if the configured server is healthy."),
    "watch": ("server.cli.watch", "Follow one auction live from its event stream."),
}
"""Command name → (module exposing ``command``, one-line help)."""
INTERRUPTED = 130
"""The exit code of a command stopped by Ctrl-C (SIGINT): the shell's 128 + 2. click's own
abort exits 1, which ``srd screen`` (rejected) and ``srd watch`` (failed or cancelled) give a
meaning of their own."""


TERMINATED = 143
"""The exit code of a command stopped by SIGTERM (``kill``, ``timeout``): 128 + 15."""
OUTPUT_LOST = 74
"""The exit code of a command whose standard output no longer took what it wrote (a full disk,
a reader gone): sysexits' ``EX_IOERR``, never a code a command gives its result."""


class OutputLostError(Exception):
    """Standard output no longer takes what is written (a full disk, a reader gone)."""

    def __init__(self, error: OSError) -> None:
        super().__init__(error.strerror or str(error))
        self.why = error.strerror or str(error)


class _Output:
    """Standard output whose failed writes and flushes raise ``OutputLostError`` (else as it
    is): a command's printing, wherever it happens, then ends in one line and ``OUTPUT_LOST``
    rather than a traceback and an exit code that tells a result nobody received."""

    def __init__(self, stream: Any) -> None:
        self._stream = stream

    def write(self, text: str) -> int:
        try:
            return int(self._stream.write(text))
        except OSError as exc:
            raise OutputLostError(exc) from exc

    def flush(self) -> None:
        try:
            self._stream.flush()
        except OSError as exc:
            raise OutputLostError(exc) from exc

    def __getattr__(self, name: str) -> Any:
        return getattr(self._stream, name)


def _drop_output() -> None:
    """Send what is left in standard output's buffer to ``/dev/null``: the interpreter's own
    flush at exit then fails no second time."""
    with contextlib.suppress(OSError, ValueError):
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, 1)  # standard output's descriptor
        os.close(devnull)


def _output_lost(error: OutputLostError) -> SystemExit:
    _drop_output()
    message = f"error: cannot write to standard output: {error.why}; the result is lost"
    click.echo(message, err=True)
    return SystemExit(OUTPUT_LOST)


class Interrupted(click.ClickException):
    """Ctrl-C (SIGINT) stopped the command: "Aborted!" on stderr, exit ``INTERRUPTED``."""

    exit_code = INTERRUPTED

    def __init__(self, partial: dict[str, Any] | None = None) -> None:
        super().__init__("aborted")
        self.partial = partial
        """What the command had made when it stopped, for its ``--json`` object."""

    def show(self, file: Any = None) -> None:
        click.echo(err=True)  # closes the terminal's ^C echo, as click does
        click.echo("Aborted!", err=True)


class Terminated(Interrupted):
    """SIGTERM stopped the command: the same way out as Ctrl-C, exit ``TERMINATED``."""

    exit_code = TERMINATED


class _TerminateRequest(KeyboardInterrupt):
    """SIGTERM, raised where the command runs, so that it stops as Ctrl-C stops it (its
    ``finally`` blocks run, ``--json`` prints its object) instead of dying mid-write."""


def _on_terminate(signum: int, frame: Any) -> None:
    raise _TerminateRequest


@contextmanager
def _interruptible() -> Iterator[None]:
    """A ``KeyboardInterrupt`` (SIGINT, which ``srd serve`` re-raises after its graceful stop)
    becomes ``Interrupted``: click would make it an abort, exit 1; SIGTERM ``Terminated``
    (but in ``srd serve``, which takes SIGTERM as uvicorn does, for its graceful stop)."""
    try:
        yield
    except _TerminateRequest as exc:
        raise Terminated(getattr(exc, "partial", None)) from exc
    except KeyboardInterrupt as exc:
        raise Interrupted(getattr(exc, "partial", None)) from exc


@contextmanager
def loading() -> Iterator[None]:
    """Import a command's modules without the cyclic garbage collector, then freeze them.

    torch and pydantic create hundreds of thousands of long-lived objects while they load; each
    collection meanwhile rescans all of them and finds nothing to free. Collecting once and
    moving what was loaded to the permanent generation (``gc.freeze``) leaves later collections
    only the objects the command itself creates.
    """
    enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        gc.collect()
        gc.freeze()
        if enabled:
            gc.enable()


class _Commands(click.Group):
    """A group whose commands are imported on first use; the listing needs no import."""

    def list_commands(self, ctx: click.Context) -> list[str]:
        experiments = [name for name, kind in KINDS.items() if kind.command]
        return [*HAND_WRITTEN, *experiments]

    def make_context(
        self,
        info_name: str | None,
        args: list[str],
        parent: click.Context | None = None,
        **extra: Any,
    ) -> click.Context:
        with _interruptible():
            return super().make_context(info_name, args, parent, **extra)

    def invoke(self, ctx: click.Context) -> Any:
        with _interruptible():  # the command's import, its options, its run
            return super().invoke(ctx)

    def get_command(self, ctx: click.Context, cmd_name: str) -> click.Command | None:
        if cmd_name in HAND_WRITTEN:
            with loading():
                module = importlib.import_module(HAND_WRITTEN[cmd_name][0])
            command: click.Command = module.command
            return command
        kind = KINDS.get(cmd_name)
        if kind is None or not kind.command:
            return None
        with loading():
            from server.cli.experiment import experiment_command

            return experiment_command(kind)

    def main(self, args: Sequence[str] | None = None, *rest: Any, **options: Any) -> Any:
        """A usage error (a bad or unknown option, a missing argument) is one line on stderr
        naming the option, exit 2, without click's usage block. Under ``--json`` a failure
        click finds in the options, an interruption (Ctrl-C, exit 130), or an unexpected error,
        still prints one JSON object on stdout (``words.json_failure``); the exit code is
        click's."""
        argv = list(sys.argv[1:] if args is None else args)
        if not options.get("standalone_mode", True):
            return super().main(argv, *rest, **options)
        json_output = "--json" in argv
        command = argv[0] if argv else None
        try:
            code = super().main(argv, *rest, **{**options, "standalone_mode": False})
        except Interrupted as exc:
            exc.show()
            if json_output:
                json_failure("aborted", command=command, extra=exc.partial)
            raise SystemExit(exc.exit_code) from exc
        except click.exceptions.NoArgsIsHelpError as exc:  # `srd` alone: the help
            exc.show()
            raise SystemExit(exc.exit_code) from exc
        except click.ClickException as exc:
            if isinstance(exc, click.UsageError):
                where = f" (see '{exc.ctx.command_path} --help')" if exc.ctx else ""
                click.echo(f"error: {exc.format_message()}{where}", err=True)
            else:
                exc.show()
            if json_output:
                param = getattr(exc, "param", None)
                option = param.opts[0] if isinstance(param, click.Option) else None
                option = option or getattr(exc, "option_name", None)  # one that does not exist
                message = exc.format_message()
                errors = [{"option": option, "message": message}] if option else None
                json_failure(message, errors, command=command)
            raise SystemExit(exc.exit_code) from exc
        except click.Abort as exc:  # click's own (a Ctrl-C it caught before ours could)
            click.echo("Aborted!", err=True)
            if json_output:
                json_failure("aborted", command=command)
            raise SystemExit(INTERRUPTED if json_output else 1) from exc
        except OutputLostError as exc:  # a full disk, a reader gone: one line, no traceback
            raise _output_lost(exc) from None
        except Exception as exc:  # the traceback goes to stderr as usual
            if json_output:
                json_failure(f"{type(exc).__name__}: {exc}", command=command)
            raise
        raise SystemExit(code if isinstance(code, int) else 0)

    def format_commands(self, ctx: click.Context, formatter: click.HelpFormatter) -> None:
        rows = [(name, help_line) for name, (_, help_line) in HAND_WRITTEN.items()]
        rows += [(name, kind.summary) for name, kind in KINDS.items() if kind.command]
        rows = [(name, plain(line)) for name, line in rows]
        with formatter.section("Commands"):
            formatter.write_dl(rows)


cli = _Commands(name="srd", help=HELP, no_args_is_help=True)


def main() -> None:
    """Console-script entry point. With standard output closed (``>&-``) a ``--json`` run is
    refused before it starts (exit 2: its one object would have nowhere to go); any other
    command runs with its printed output discarded, its exit code telling the result. Standard
    output that fails a write (a full disk, a reader gone) ends the command with one line and
    exit ``OUTPUT_LOST`` (74)."""
    if sys.stdout is None:
        if "--json" in sys.argv[1:]:
            click.echo("error: --json: standard output is closed; nothing was run", err=True)
            raise SystemExit(2)
        sys.stdout = open(os.devnull, "w")  # noqa: SIM115 (for the process's life)
    if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:  # a script's background job
        signal.signal(signal.SIGINT, signal.default_int_handler)  # (`srd … &`): still stoppable
    if sys.argv[1:2] == ["serve"]:  # which stops gracefully on SIGTERM, as uvicorn does
        cli(prog_name="srd")
        return
    signal.signal(signal.SIGTERM, _on_terminate)
    sys.stdout = _Output(sys.stdout)
    try:
        cli(prog_name="srd")
    finally:  # what the command printed last may still be in the buffer
        try:
            sys.stdout.flush()
        except OutputLostError as exc:
            raise _output_lost(exc) from None
