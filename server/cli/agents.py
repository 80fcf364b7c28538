"""``srd agents``: a population of remote agents that submit their models, join a remote
fine-tuning auction and fine-tune themselves over HTTP (``agents.remote``)."""

from __future__ import annotations

import asyncio
import ipaddress
import json
import sys
from collections import Counter
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

import click
from rich.console import Console
from rich.markup import escape
from rich.progress import BarColumn, Progress, TaskID, TextColumn, TimeElapsedColumn
from rich.table import Column, Table

from agents.remote import (
    AUCTION_WAIT_S,
    GIVE_UP_S,
    MAX_AGENTS,
    TRANSPORTS,
    PopulationConfig,
    PopulationReport,
    RemoteError,
    SoFar,
    Transport,
    run_population,
)
from server.api.schemas import MAX_FINE_TUNE_ROUNDS, MAX_ROW_ID, MAX_SEED, ROUND_DEADLINE_S
from server.cli.launch import server_url
from server.cli.words import FiniteRange, IntegerRange, json_failure

OPTIONS = {
    "tokens_file": "--tokens",
    "fine_tune_rounds": "--rounds",
    "round_deadline_s": "--deadline",
    "give_up_s": "--give-up",
    "auction_wait_s": "--wait",
}
"""``PopulationConfig`` fields whose option is not the field's name with dashes."""


def _option_of(problem: str) -> str:
    """The option a ``PopulationConfig`` problem is about (it starts with the field's name;
    ``honest + saboteurs`` is said of ``--honest``)."""
    field = problem.split()[0]
    return OPTIONS.get(field, "--" + field.replace("_", "-"))


GAVE_UP = 1
"""Exit code when the server could not be reached or refused the population."""
INVALID = 2
"""Exit code of invalid options."""


def _local_operator_token(server: str, err: Console) -> tuple[str | None, Path | None]:
    """The operator token ``srd serve`` wrote into its data folder on this machine
    (``SRD_DATA_DIR``, default ./data), for a server on a loopback address: the token never
    leaves the machine. None if there is no such server or file; and the file looked at (None
    for a server elsewhere)."""
    from server.config import Settings

    host = urlsplit(server).hostname or ""
    try:
        loopback = host == "localhost" or ipaddress.ip_address(host).is_loopback
        path = Settings().admin_token_file  # where srd serve writes it, as it reads the settings
    except ValueError:  # not an IP address, or settings srd serve would refuse too
        return None, None
    if not loopback:
        return None, None
    try:
        token = path.read_text(encoding="ascii").strip()
    except (OSError, UnicodeDecodeError):
        return None, path
    if not token:
        return None, path
    err.print(f"operator token: {path} (this machine's srd serve)", highlight=False)
    return token, path


def _say_stopped(err: Console, made: dict[str, Any], tokens_file: Path | None) -> None:
    """What a run stopped midway had made: its models, their auction, where the tokens are."""
    agents, auctions = made["registered"], made["auctions"]
    if not agents:
        return
    ids = ", ".join(str(a["model_id"]) for a in agents[:20]) + (", …" if len(agents) > 20 else "")
    where = f" in auction {auctions[0]}" if auctions else ""
    tokens = (  # the file this run wrote (one from an earlier run holds other tokens)
        f"their tokens are in {tokens_file}"
        if tokens_file is not None
        else "their tokens are lost (--tokens keeps them, once every agent has registered)"
    )
    err.print(
        f"stopped: {len(agents)} models registered{where} (model ids {ids}); {tokens}",
        highlight=False,
        soft_wrap=True,  # one line, whatever the width: a script may grep it
    )


def _agents_table(report: PopulationReport) -> Table:
    """One row per agent, then the totals."""
    table = Table(
        Column("Participant", overflow="fold"),  # whole: names differ at their ends
        "Model",
        "Submitted",
        "Uploads accepted",
        "Refused",
        "Held",
        "Late",
        "Missing",
        "Final version",
        "In the auction",
        "Bytes up",
        "Bytes down",
        title=f"remote agents on {escape(report.server)}",
        show_footer=True,
    )
    for row in report.per_agent:
        uploads = row["uploads"]
        table.add_row(
            escape(row["participant"]),
            str(row["model_id"]),
            row["submitted"],
            str(uploads["accepted"]),
            str(uploads["refused"]),
            str(uploads["held"]),
            str(uploads["late"]),
            str(uploads["missing"]),
            str(row["version"]),
            _in_the_auction(row),
            f"{row['bytes_up']:,}",
            f"{row['bytes_down']:,}",
        )
    submitted = Counter(row["submitted"] for row in report.per_agent)
    footers = [
        f"{report.agents} agents",
        "",
        ", ".join(f"{n} {status}" for status, n in sorted(submitted.items())),
        str(report.uploads["accepted"]),
        str(report.uploads["refused"]),
        str(report.uploads["held"]),
        str(report.uploads["late"]),
        str(sum(row["uploads"]["missing"] for row in report.per_agent)),
        "",
        f"{report.errors} stopped by an error" if report.errors else "",
        f"{report.bytes_up:,}",
        f"{report.bytes_down:,}",
    ]
    for column, footer in zip(table.columns, footers, strict=True):
        column.footer = footer
    return table


def _in_the_auction(row: dict[str, Any]) -> str:
    """What an agent's patron did, or the error that stopped the agent."""
    if "error" in row:
        return f"error: {escape(row['error'][:80])}"
    if row["result"] == "bought":
        return f"bought at {row['price']:.3f}"
    return str(row["result"])


def _summary(report: PopulationReport) -> Table:
    """The population and its auction."""
    table = Table(show_header=False, box=None)
    auction = report.auction
    rows = [
        ("Agents", f"{report.agents} ({report.honest} honest, {report.saboteurs} saboteurs)"),
        ("Admitted at submission", str(report.admitted)),
        ("Auction", f"{auction['id']}: {auction['status']} ({auction['stop_reason']})"),
        ("Iterations, fine-tuning rounds", f"{auction['iterations']}, {report.rounds}"),
        ("Buyers, revenue", f"{auction['buyers']}, {auction['revenue']:.3f}"),
        ("Refused by rules", ", ".join(report.refusal_rules) or "—"),
        ("Requests (retries)", f"{report.requests} ({report.retries}), {report.transport}"),
        ("Elapsed", f"{report.elapsed_s:.1f} s"),
    ]
    for name, value in rows:
        table.add_row(name, escape(value))
    return table


@click.command("agents")
@click.option(
    "--server",
    required=True,
    callback=server_url,
    help="Base URL of the auction house, e.g. http://127.0.0.1:8000.",
)
@click.option(
    "--honest",
    type=IntegerRange(0, MAX_AGENTS),
    default=6,
    show_default=True,
    help="Honest agents (the paper's randomisation), fine-tuning faithfully.",
)
@click.option(
    "--saboteurs",
    type=IntegerRange(0, MAX_AGENTS),
    default=0,
    show_default=True,
    help="Bait-and-switch agents: honest-looking model, then always-hold uploads.",
)
@click.option(
    "--auction",
    type=IntegerRange(1, MAX_ROW_ID),
    default=None,
    help="An enrolling auction (created with enrollment_s) for the agents' accepted models "
    "to join; one that takes no patrons is refused before anything is registered [default: "
    "wait for one containing the agents' models, or create one with --admin-token].",
)
@click.option(
    "--seed",
    type=IntegerRange(0),
    default=0,
    show_default=True,
    help="Seeds the agents' models: same seed, same models.",
)
@click.option(
    "--admin-token",
    envvar="SRD_ADMIN_TOKEN",
    default=None,
    help="Operator token: create a remote auction of the agents' models. Prefer "
    "SRD_ADMIN_TOKEN: a command line is visible to every user of the machine (ps). "
    "[default: for a server on a loopback address, the token file its srd serve generated "
    "in SRD_DATA_DIR (./data)]",
)
@click.option(
    "--rarity",
    type=FiniteRange(0, 1, min_open=True),
    default=0.5,
    show_default=True,
    help="Created auction's supply: fish on sale per patron (fish = int(rarity × agents)).",
)
@click.option(
    "--rounds",
    type=IntegerRange(1, MAX_FINE_TUNE_ROUNDS),
    default=4,
    show_default=True,
    help="Created auction: fine-tuning rounds.",
)
@click.option(
    "--deadline",
    type=FiniteRange(*ROUND_DEADLINE_S),
    default=10.0,
    show_default=True,
    help="Created auction: seconds a round waits at most.",
)
@click.option(
    "--auction-seed",
    type=IntegerRange(0, MAX_SEED),
    default=0,
    show_default=True,
    help="Created auction: its seed.",
)
@click.option(
    "--give-up",
    type=FiniteRange(1, 3600),
    default=GIVE_UP_S,
    show_default=True,
    help="Seconds a failing request is retried before giving up (exit 1).",
)
@click.option(
    "--wait",
    "auction_wait",
    type=FiniteRange(0, 86_400),
    default=AUCTION_WAIT_S,
    show_default=True,
    help="Seconds to wait for an auction containing the agents' models.",
)
@click.option(
    "--name-prefix",
    default=None,
    help="Participant names start with this [default: agents-<seed>-<random tag>].",
)
@click.option(
    "--transport",
    type=click.Choice(TRANSPORTS),
    default="http",
    show_default=True,
    help="Rounds by long poll and PUT, or over one round socket per agent.",
)
@click.option(
    "--tokens",
    "tokens_file",
    type=click.Path(dir_okay=False, writable=True, path_type=Path),
    default=None,
    help="Write each agent's participant, model id and token to this JSON file (mode 0600) "
    "once registered: the models can then be played on without this run.",
)
@click.option(
    "--json", "json_output", is_flag=True, help="Print exactly one JSON object on stdout."
)
def command(
    server: str,
    honest: int,
    saboteurs: int,
    auction: int | None,
    seed: int,
    admin_token: str | None,
    rarity: float,
    rounds: int,
    deadline: float,
    auction_seed: int,
    give_up: float,
    auction_wait: float,
    name_prefix: str | None,
    transport: Transport,
    tokens_file: Path | None,
    json_output: bool,
) -> None:
    """Run remote agents that submit and fine-tune over HTTP: register the population, join
    (or wait for, or create) a remote fine-tuning auction, answer every round with each
    agent's own fine-tuning, follow the auction to its end and summarise."""  # fmt: skip
    err = Console(stderr=True)
    waiting = None  # said once the options are read: the agents will wait for an auction
    if admin_token is None and auction is None:
        admin_token, looked_at = _local_operator_token(server, err)
        if admin_token is None:
            where = (
                f"none in {looked_at.resolve()}, where srd serve writes it when its data folder "
                "is this one: SRD_DATA_DIR names the server's"
                if looked_at is not None
                else "the server is not on this machine"
            )
            tokens = "their tokens are kept" if tokens_file else "--tokens keeps their tokens"
            waiting = (
                f"no --auction and no operator token ({where}): once registered, the agents "
                f"wait up to {auction_wait:g} s (--wait) for an auction that takes their models "
                f"(--admin-token or SRD_ADMIN_TOKEN creates one; {tokens})"
            )
    try:
        config = PopulationConfig(
            server=server,
            honest=honest,
            saboteurs=saboteurs,
            seed=seed,
            auction=auction,
            admin_token=admin_token,
            rarity=rarity,
            fine_tune_rounds=rounds,
            round_deadline_s=deadline,
            auction_seed=auction_seed,
            give_up_s=give_up,
            auction_wait_s=auction_wait,
            name_prefix=name_prefix,
            transport=transport,
            tokens_file=tokens_file,
        )
    except ValueError as exc:  # the options named in the message
        problems = str(exc).split("; ")
        for problem in problems:
            err.print(
                f"[red]error:[/red] {_option_of(problem)}: {escape(problem)}", highlight=False
            )
        if json_output:
            json_failure(str(exc), [{"option": _option_of(p), "message": p} for p in problems])
        raise SystemExit(INVALID) from exc
    if waiting is not None:
        err.print(waiting, highlight=False, soft_wrap=True)
    import torch  # only for a run: a bad option is told without loading it

    torch.set_num_threads(1)  # each agent fine-tunes one tiny model: more threads only contend
    with Progress(
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        TextColumn("{task.completed}/{task.total}"),
        TimeElapsedColumn(),
        console=err,
        disable=not sys.stderr.isatty(),
    ) as bar:
        tasks: dict[str, TaskID] = {}

        def progress(stage: str, done: int, total: int) -> None:
            if stage not in tasks:
                tasks[stage] = bar.add_task(stage, total=total)
            bar.update(tasks[stage], completed=done, total=max(total, done))

        so_far = SoFar()
        try:
            report = asyncio.run(run_population(config, progress, so_far))
        except KeyboardInterrupt as exc:  # what was made, before "Aborted!" (exit 130)
            made = so_far.to_dict()
            _say_stopped(err, made, tokens_file if so_far.tokens_saved else None)
            exc.partial = made  # type: ignore[attr-defined]  # --json's object carries it
            raise
        except (RemoteError, ValueError, KeyError, TypeError) as exc:
            message = str(exc)
            if not isinstance(exc, RemoteError):  # an answer not shaped as this service's
                message = (
                    f"the server at {server} answered something this client cannot read (is it "
                    f"an srd server?): {type(exc).__name__}: {exc}"
                )
            err.print(f"[red]error:[/red] {escape(message)}", highlight=False)
            if json_output:
                json_failure(message)
            raise SystemExit(GAVE_UP) from exc
    if json_output:
        sys.stdout.write(json.dumps(report.to_dict()) + "\n")
    else:
        out = Console(highlight=False, width=None if sys.stdout.isatty() else 160)
        out.print(_agents_table(report))
        out.print(_summary(report))
    if report.errors:  # the others played on; the rows say what stopped these
        err.print(f"[red]error:[/red] {report.errors} agents stopped by an error", highlight=False)
        raise SystemExit(GAVE_UP)
