"""The experiment commands, generated from the config dataclasses (``sim.experiment``).

Each config field becomes one option: ``--name-with-dashes``, its docstring as help, its default
and bounds shown; flags are ``--x/--no-x``, lists are comma-separated. Every command also takes
``--out DIR`` and ``--json``. The values are validated by ``sim.experiment.parse_config``, the
same code that validates job parameters, so the CLI and ``POST /jobs`` agree on every option.

Without ``--json`` the command prints a short summary (the kind's headline numbers, a table of
its rows and the artifact folder) on stdout; with ``--json`` exactly one JSON object, the run's
result plus ``out_dir``. Progress goes to stderr, as a bar on a terminal.
"""

from __future__ import annotations

import contextlib
import errno
import json
import shutil
import sys
import tempfile
from pathlib import Path
from typing import Any

import click
from click.core import ParameterSource
from rich.console import Console
from rich.markup import escape
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table

from server.cli import loading
from server.cli.words import FiniteRange, header, json_failure, plain, rounded
from server.config import Settings
from sim.experiment import (
    MAX_NUMBER_CHARS,
    ConfigError,
    ConfigField,
    config_fields,
    default_out_dir,
    json_safe,
    over_budget,
    parse_config,
    read_number,
    write_json,
)
from studies.registry import ExperimentKind

INVALID = 2
"""Exit code of an invalid option (as click's own usage errors)."""
CLI_BUDGET_S = 86_400.0
"""The compute a run may need by default (``--budget-s``), estimated as a job's is: a day on
one core. Options that would keep the machine busy for days (a typo in ``--trials``) are refused
before the run, naming the option to lower; a longer run raises it."""
WORKER_TORCH_THREADS = Settings.model_fields["worker_torch_threads"].default
"""Torch threads of an experiment run from the command line: the job workers' default (the
experiments' tensors are small; on a busy machine more threads only contend)."""


def _shown(value: Any) -> str:
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, tuple | list):
        return ",".join(str(v) for v in value)
    return str(value)


def _option(field: ConfigField) -> click.Option:
    flag = "--" + field.name.replace("_", "-")
    detail = []
    if field.bounds:
        detail.append(field.bounds)
    if field.kind == "list":
        detail.append("comma-separated, or the option given again")
    help_text = plain(field.help) + (f" [{'; '.join(detail)}]" if detail else "")
    if field.kind == "bool":
        return click.Option(
            [f"{flag}/--no-{flag[2:]}", field.name],
            default=field.default,
            show_default=True,
            help=help_text,
        )
    types: dict[str, click.ParamType[Any]] = {
        "int": click.INT,
        "float": click.FLOAT,
        "str": click.STRING,
    }
    param_type: click.ParamType[Any] = (
        click.Choice(field.choices)
        if field.kind == "choice"
        else types.get(field.kind, click.STRING)
    )
    default = None if field.default is None else _shown(field.default)
    if field.kind == "list":  # given twice, its values add up: --backswing 1 --backswing 2,3
        return click.Option(
            [flag, field.name],
            type=param_type,
            multiple=True,
            callback=_joined,
            default=() if default is None else (default,),
            show_default=default is not None,
            help=help_text,
        )
    return click.Option(
        [flag, field.name],
        type=param_type,
        default=field.default,
        show_default=default is not None,
        help=help_text,
    )


def _joined(_ctx: click.Context, _param: click.Parameter, value: tuple[str, ...]) -> str | None:
    """A list option given several times: all its values, in the order given."""
    return ",".join(value) if value else None


def experiment_command(kind: ExperimentKind) -> click.Command:
    """The ``srd <kind>`` command: one option per config field, plus ``--out`` and ``--json``."""
    fields = config_fields(kind.config_class())
    params: list[click.Parameter] = [_option(f) for f in fields]
    params += [
        click.Option(
            ["--out", "out"],
            type=click.Path(file_okay=False),
            callback=_out_folder,
            default=None,
            help="Artifacts folder [default: runs/<command>__<seed>__<YYYYmmdd-HHMMSS>/].",
        ),
        click.Option(
            ["--json", "json_output"],
            is_flag=True,
            default=False,
            help="Print exactly one JSON object on stdout.",
        ),
        click.Option(
            ["--budget-s", "budget_s"],
            type=FiniteRange(min=1, max=1e9),
            default=CLI_BUDGET_S,
            show_default=True,
            help="The most compute a run may need, in seconds on one core, as estimated before "
            "it starts: a run over it is refused, naming the option to lower (raise this to run "
            "it anyway).",
        ),
    ]

    def callback(out: Path | None, json_output: bool, budget_s: float, **values: Any) -> None:
        # only what the command line gave: an option given is checked against the others
        # (``--nominal --trials 7`` is refused though 7 is the default)
        source = click.get_current_context().get_parameter_source
        options = {
            name: value
            for name, value in values.items()
            if value is not None and source(name) is not ParameterSource.DEFAULT
        }
        execute(kind, options, out=out, json_output=json_output, budget_s=budget_s)

    return click.Command(
        kind.name, params=params, callback=callback, help=plain(kind.config_class().__doc__ or "")
    )


def _element_message(field: str, message: str, options: dict[str, Any]) -> str:
    """The error of one element of a comma-separated list option (``field`` ``name.index``, as
    ``parse_config`` names it) with the element's position from 1 in the value as typed:
    ``element 2 of '1,,2' is empty``, ``element 2 of '1,x,2': 'x' is not a number``; any
    other error as it is. (Every list option of the experiments is a list of numbers.)"""
    name, _, index = field.partition(".")
    given = options.get(name)
    parts = given.split(",") if isinstance(given, str) else []
    if not index.isdigit() or int(index) >= len(parts):
        return message
    part = parts[int(index)].strip()
    where = f"element {int(index) + 1} of {_cut(str(given))!r}"
    if not part:
        return f"{where} is empty"
    if len(part) > MAX_NUMBER_CHARS:
        return f"{where}: {len(part)} characters, too long for a number"
    if read_number(part) is None:
        return f"{where}: {_cut(part)!r} is not a number"
    return f"{where} ({part}): {message}"


def _cut(text: str, most: int = 40) -> str:
    """``text``, cut to ``most`` characters (an error line quotes what was typed)."""
    return text if len(text) <= most else text[: most - 1] + "…"


def _out_folder(_ctx: click.Context, _param: click.Parameter, value: str | None) -> Path | None:
    """``--out``: a folder's path, not an empty word (which would write into the current
    folder)."""
    if value is None:
        return None
    if not value.strip():
        raise click.BadParameter("must name a folder (it is empty)")
    return Path(value)


def _unwritable(folder: Path) -> str | None:
    """Why no file can be written into ``folder``, or None (tried, not guessed from its mode
    bits: a read-only mount or an immutable folder refuses even root)."""
    try:
        with tempfile.TemporaryFile(dir=folder):
            return None
    except OSError as exc:
        return f"cannot write into the folder {folder}: {exc.strerror or exc}"


def execute(
    kind: ExperimentKind,
    options: dict[str, Any],
    *,
    out: Path | None,
    json_output: bool,
    budget_s: float = CLI_BUDGET_S,
) -> dict[str, Any]:
    """Validate the options (a run whose estimated compute is over ``budget_s`` is refused, as
    a job over the server's budget is), run the experiment with a progress bar, print its
    result."""
    stderr = Console(stderr=True, soft_wrap=True)  # an error line stays one line in a log
    try:  # the options are read from the config alone: a bad one is told before torch loads
        config = parse_config(kind.config_class(), options)
        too_much = over_budget(config, budget_s, "--budget-s")
        if too_much is not None:
            raise too_much
    except ConfigError as exc:
        errors = []
        for err in exc.errors:
            field = err["field"].split(".")[0]
            option = "--" + field.replace("_", "-") if field else "--budget-s"
            message = _element_message(err["field"], err["message"], options)
            errors.append({"option": option, "message": message})
            stderr.print(f"[red]error:[/red] {option}: {escape(message)}", highlight=False)
        if json_output:
            json_failure(f"{errors[0]['option']}: {errors[0]['message']}", errors)
        raise SystemExit(INVALID) from exc
    out_dir = out or Path("runs")  # (the default's folder, named if it cannot be made)
    created = out is None or not out.exists()
    try:
        out_dir = out or default_out_dir(kind.name, int(getattr(config, "seed", 0)))
        out_dir.mkdir(parents=True, exist_ok=True)
        problem = _unwritable(out_dir)
    except OSError as exc:  # a folder that cannot be made: one line and exit 2, like any option
        problem = f"cannot create the folder {out_dir}: {exc.strerror or exc}"
    if problem is not None:  # said before the run, not after it
        stderr.print(f"[red]error:[/red] --out: {escape(problem)}", highlight=False)
        if json_output:
            json_failure(f"--out: {problem}", [{"option": "--out", "message": problem}])
        raise SystemExit(INVALID)
    with loading():  # the experiment's code, and torch with it, for a run that will happen
        _, runner = kind.load()
        import torch
    torch.set_num_threads(WORKER_TORCH_THREADS)  # one thread, as the job workers run it
    before = set(out_dir.iterdir())
    try:
        result = _run(kind, runner, config, out_dir, stderr)
        write_json(out_dir / "result.json", result)
    except BaseException as exc:  # failed or interrupted: what this run wrote goes
        _remove_written(out_dir, before, created)
        if not isinstance(exc, OSError) or exc.errno not in WRITE_ERRORS:
            raise
        # the disk full, a folder made read-only meanwhile: the machine's, said in one line
        where = f" ({exc.filename})" if exc.filename else ""
        problem = f"cannot write the run's files{where}: {exc.strerror or exc}"
        stderr.print(f"[red]error:[/red] {escape(problem)}", highlight=False)
        if json_output:
            json_failure(problem)
        raise SystemExit(1) from exc
    if json_output:
        shown = json_safe({**result, "out_dir": str(out_dir)})
        sys.stdout.write(json.dumps(shown, allow_nan=False) + "\n")
    else:
        width = None if sys.stdout.isatty() else 160  # logs and pipes get whole tables
        print_summary(kind, result, out_dir, Console(highlight=False, width=width))
    return result


WRITE_ERRORS = {
    errno.ENOSPC,
    errno.EDQUOT,
    errno.EFBIG,
    errno.EROFS,
    errno.EACCES,
    errno.EPERM,
    errno.EIO,
    errno.EISDIR,
    errno.ENOTDIR,
    errno.EEXIST,
}
"""The errors of a file that cannot be written (the disk full, read-only, in the way): said in
one line; any other error keeps its traceback."""


def _remove_written(out_dir: Path, before: set[Path], created: bool) -> None:
    """Remove what a failed or interrupted run wrote: the folder it made, or what it added to
    a folder that was there (no half-written file stays)."""
    if created:
        shutil.rmtree(out_dir, ignore_errors=True)
        return
    with contextlib.suppress(OSError):
        for path in set(out_dir.iterdir()) - before:
            if path.is_dir() and not path.is_symlink():
                shutil.rmtree(path, ignore_errors=True)
            else:
                path.unlink(missing_ok=True)


def _run(
    kind: ExperimentKind, runner: Any, config: Any, out_dir: Path, stderr: Console
) -> dict[str, Any]:
    """The experiment run with a progress bar on stderr (a terminal's): its result."""
    with Progress(
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        TextColumn("{task.percentage:>3.0f}%"),
        TimeElapsedColumn(),
        TextColumn("{task.fields[message]}"),
        console=stderr,
        disable=not sys.stderr.isatty(),
    ) as bar:
        task = bar.add_task(kind.name, total=1.0, message="")

        def progress(fraction: float, message: str) -> None:
            bar.update(task, completed=min(max(fraction, 0.0), 1.0), message=message)

        result: dict[str, Any] = runner(config, out_dir=out_dir, progress=progress)
        progress(1.0, "done")
    return result


def _cell(value: Any) -> str:
    if value is None:
        return "—"
    if isinstance(value, float):
        return rounded(value)
    return str(value)


def print_summary(
    kind: ExperimentKind, result: dict[str, Any], out_dir: Path, out: Console
) -> None:
    """The headline numbers, the table of rows and the artifact folder, for a person."""
    headline = Table(show_header=False, box=None, title=f"srd {kind.name}", title_justify="left")
    for name in kind.headline:
        if name in result and not isinstance(result[name], dict | list):
            headline.add_row(header(name), escape(_cell(result[name])))
    if "elapsed_s" in result:
        headline.add_row(header("elapsed_s"), _cell(result["elapsed_s"]))
    out.print(headline)
    rows = result.get(kind.table) if kind.table else None
    if isinstance(rows, list) and rows and isinstance(rows[0], dict):
        columns = [c for c in kind.columns if c in rows[0]]
        table = Table(*(header(c) for c in columns))
        for row in rows:
            table.add_row(*(escape(_cell(row.get(c))) for c in columns))
        out.print(table)
    if isinstance(result.get("caption"), str):  # what each configuration is, in words
        out.print(escape(result["caption"]))
    out.print(f"artifacts: {escape(str(out_dir))}")
