"""``srd watch AUCTION_ID``: follow one auction live from its event stream
(``GET /auctions/{id}/events``) until it ends.

A terminal gets a live table (rich); a pipe or a log gets one plain line per event; ``--json``
prints only the final state (``GET /auctions/{id}``) as one JSON object. A dropped stream is
opened again, resuming after the last event received (``Last-Event-ID``), for as long as
``--reconnect-s`` allows since its last event: a server restart or a database outage is waited
out.
"""

from __future__ import annotations

import json
import math
import sys
import time
from collections import Counter
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from functools import partial
from typing import Any, TypeAlias

import click
import httpx
from click.core import ParameterSource
from rich.console import Console, Group
from rich.live import Live
from rich.markup import escape
from rich.table import Table
from rich.text import Text

from server.cli.launch import server_url
from server.cli.words import FiniteRange, IntegerRange, json_failure

FINISHED, ENDED_OTHERWISE, LOST = 0, 1, 3
"""Exit codes: the auction finished; it failed or was cancelled; it could not be followed
(server unreachable, unknown auction, the stream gone for longer than ``--reconnect-s``)."""
TIMEOUT = httpx.Timeout(10.0, read=120.0)
"""An idle stream sends a keep-alive every 15 s by default: 120 s of silence is a dead one."""
LIVE_ROWS = 20
"""The most recent iterations the live table shows (a terminal is only so tall)."""
MAX_AUCTION_ID = 2**31 - 1
"""The largest auction id the API takes (``server.api.schemas.MAX_ROW_ID``, not imported: it
would load FastAPI, tripling this command's start)."""
RECONNECT_S = 60.0
"""How long a dropped stream is opened again, from its last event or the last time it stayed
open, before ``watch`` gives up
(the default of ``--reconnect-s``): a server's restart takes seconds."""
RETRY_PAUSES_S = (0.0, 1.0, 2.0, 4.0, 5.0)
"""The waits before each attempt to open a dropped stream again (then the last, repeated)."""
HELD_S = 1.0
"""A stream that stayed open this long was had again: its drop starts a new wait (one that
opens and closes at once is still the same drop)."""
AGAIN = frozenset({429, 502, 503, 504})
"""Answers a stream that was open may get while its server restarts, sheds load or waits for
its database: tried again."""
SHOWN_DATA = 120
"""How much of a piece of data that is not an event an error message quotes."""

Shape: TypeAlias = "str | dict[str, Shape] | list[Shape]"
"""What ``watch`` reads of a piece of JSON: ``WHOLE``, ``NUMBER``, ``TEXT`` or ``MAYBE_TEXT``;
an object whose keys hold those shapes (a key ending in ``?`` may be absent); ``[shape]``, a
list of them."""
WHOLE, NUMBER, TEXT, MAYBE_TEXT = "a whole number", "a finite number", "text", "text or null"
PATRON: dict[str, Shape] = {"participant": TEXT, "version": WHOLE}
EVENTS: dict[str, Shape] = {
    "iteration": {
        "iteration": WHOLE,
        "price": NUMBER,
        "n_available": WHOLE,
        "n_available_after": WHOLE,
        "next_price": NUMBER,
        "votes": {"buy": WHOLE, "hold": WHOLE, "quit": WHOLE},
        "purchases?": [{**PATRON, "price": NUMBER}],
        "quits?": [PATRON],
    },
    "round": {"round": WHOLE, "iteration": WHOLE, "status": TEXT, "answers?": [{"outcome": TEXT}]},
    "end": {
        "status": TEXT,
        "iterations": WHOLE,
        "price": NUMBER,
        "n_initial": WHOLE,
        "n_sold?": WHOLE,
        "stop_reason?": MAYBE_TEXT,
        "error?": MAYBE_TEXT,
    },
}
"""The fields of each event ``watch`` reads (an event of another name is skipped)."""
FINAL: Shape = {"id": WHOLE, "status": TEXT}
"""What ``--json`` reads of ``GET /auctions/{id}`` before printing it."""


class WatchError(Exception):
    """The auction could not be followed; the message says why."""


class NotAnEventError(ValueError):
    """A piece of data is not what an srd server sends; the message says where."""


def _kind(value: Any) -> str:
    """What a piece of JSON is, in words."""
    if value is None:
        return "null"
    names = {bool: "a boolean", dict: "an object", list: "a list", str: "text"}
    return names.get(type(value), "a number")


def check(value: Any, shape: Shape, where: str = "") -> None:
    """Raise ``NotAnEventError`` unless ``value`` has ``shape`` (its path in the message)."""
    if isinstance(shape, dict):
        if not isinstance(value, dict):
            raise NotAnEventError(f"{where or 'the data'} is {_kind(value)}, not an object")
        for key, inner in shape.items():
            name = key.removesuffix("?")
            path = f"{where}.{name}" if where else name
            if name in value:
                check(value[name], inner, path)
            elif not key.endswith("?"):
                raise NotAnEventError(f"{path} is missing")
        return
    if isinstance(shape, list):
        if not isinstance(value, list):
            raise NotAnEventError(f"{where} is {_kind(value)}, not a list")
        for i, item in enumerate(value):
            check(item, shape[0], f"{where}[{i}]")
        return
    if shape == WHOLE:
        fits = isinstance(value, int) and not isinstance(value, bool)
    elif shape == NUMBER:
        fits = isinstance(value, int | float) and not isinstance(value, bool)
        fits = fits and math.isfinite(value)
    else:
        fits = isinstance(value, str) or (shape == MAYBE_TEXT and value is None)
    if not fits:
        found = json.dumps(value) if isinstance(value, float) else _kind(value)  # NaN, Infinity
        raise NotAnEventError(f"{where} is {found}, not {shape}")


def parsed(text: str | bytes, shape: Shape) -> dict[str, Any]:
    """``text`` read as JSON of ``shape`` (an object), else ``NotAnEventError`` quoting it."""
    try:
        value = json.loads(text)
    except (ValueError, RecursionError):  # not JSON (UnicodeDecodeError too), nested too deep
        raw = text if isinstance(text, str) else text.decode("utf-8", "replace")
        shown = raw if len(raw) <= SHOWN_DATA else raw[:SHOWN_DATA] + "..."
        raise NotAnEventError(f"not JSON: {shown!r}") from None
    check(value, shape)
    result: dict[str, Any] = value
    return result


@dataclass
class Watched:
    """What the stream has told so far."""

    auction_id: int
    iterations: list[dict[str, Any]] = field(default_factory=list)
    rounds: dict[int, dict[str, Any]] = field(default_factory=dict)
    """Remote fine-tuning rounds by number, as their latest event tells them."""
    end: dict[str, Any] | None = None
    last_id: str | None = None
    connected: bool = False
    """The stream was opened once (a server that never answered is not a dropped stream)."""

    def take(self, name: str, data: dict[str, Any]) -> None:
        if name == "iteration":
            self.iterations.append(data)
        elif name == "round":
            self.rounds[int(data["round"])] = data
        elif name == "end":
            self.end = data


def sse(lines: Iterator[str]) -> Iterator[tuple[str, str | None, str]]:
    """(event name, id, data) of each event of a ``text/event-stream`` body; comments and
    ``retry`` hints are skipped."""
    name, event_id, data = "message", None, list[str]()
    for line in lines:
        if not line:
            if data:
                yield name, event_id, "\n".join(data)
            name, event_id, data = "message", None, []
            continue
        key, _, value = line.partition(":")
        value = value.removeprefix(" ")
        if key == "event":
            name = value
        elif key == "id":
            event_id = value
        elif key == "data":
            data.append(value)


def follow(
    client: httpx.Client,
    watched: Watched,
    shown: Callable[[str, dict[str, Any]], None],
    *,
    reconnect_s: float = RECONNECT_S,
    dropped: Callable[[str, float], None] = lambda cause, pause: None,
) -> None:
    """Read the auction's events into ``watched`` (telling each to ``shown``) until its end
    event. A stream that drops before it is opened again after the pauses of
    ``RETRY_PAUSES_S`` (``dropped(cause, pause)`` hears each), resuming after the last event,
    until ``reconnect_s`` passed since the drop without an event or a stream held open
    ``HELD_S`` (a quiet auction's stream sends keep-alives only). A server that never answered
    is tried once more only: it is the wrong address, not a dropped stream."""
    path = f"/auctions/{watched.auction_id}/events"
    tries = 0  # attempts since the stream was last had
    since: float | None = None  # when the stream dropped (after it was last had)
    while True:
        headers = {} if watched.last_id is None else {"Last-Event-ID": watched.last_id}
        opened: float | None = None
        try:
            with client.stream("GET", path, headers=headers, params={"rounds": "true"}) as response:
                if response.status_code == 404:
                    response.read()
                    if not _srd_error(response):
                        raise WatchError(f"{_not_srd(client)} (HTTP 404 from {path})")
                    raise WatchError(f"auction {watched.auction_id} not found on {client.base_url}")
                if response.status_code in AGAIN and watched.connected:
                    response.read()
                    raise _BusyError(f"HTTP {response.status_code}: {response.text[:SHOWN_DATA]}")
                if response.status_code != 200:
                    response.read()
                    raise WatchError(f"{path}: HTTP {response.status_code}: {response.text}")
                kind = response.headers.get("content-type", "").partition(";")[0].strip()
                if kind.lower() != "text/event-stream":
                    raise WatchError(
                        f"{_not_srd(client)} event stream: {path} is {kind or 'untyped'}, "
                        "not text/event-stream"
                    )
                watched.connected = True
                opened = time.monotonic()
                for name, event_id, data in sse(response.iter_lines()):
                    if name not in EVENTS:
                        continue  # an event a later server sends: nothing to show of it
                    try:
                        payload = parsed(data, EVENTS[name])
                    except NotAnEventError as exc:
                        raise WatchError(f"{_not_srd(client)} event: {name}: {exc}") from None
                    watched.take(name, payload)
                    tries, since = 0, None
                    if event_id is not None:
                        watched.last_id = event_id
                    shown(name, payload)
                    if name == "end":
                        return
            cause = "the server closed the stream before the auction's end"
        except httpx.HTTPError as exc:
            cause = f"{type(exc).__name__}: {exc}" if str(exc) else type(exc).__name__
        except _BusyError as exc:
            cause = str(exc)
        if opened is not None and time.monotonic() - opened >= HELD_S:
            tries, since = 0, None  # it was had again: a new drop
        tries += 1
        if not watched.connected and tries > 1:
            raise WatchError(f"the server at {client.base_url} did not answer ({cause})")
        now = time.monotonic()
        since = now if since is None else since
        if now - since >= reconnect_s:
            raise WatchError(
                f"the event stream dropped and could not be had again for {reconnect_s:g} s "
                f"({cause})"
            )
        pause = RETRY_PAUSES_S[min(tries, len(RETRY_PAUSES_S)) - 1]
        pause = min(pause, max(0.0, since + reconnect_s - now))
        if watched.connected:
            dropped(cause, pause)
        time.sleep(pause)


class _BusyError(Exception):
    """An answer a restarting or busy server gives: the stream is tried again."""


def _srd_error(response: httpx.Response) -> bool:
    """Whether an error answer is this service's: JSON with a ``detail`` list."""
    try:
        body = response.json()
    except ValueError:
        return False
    return isinstance(body, dict) and isinstance(body.get("detail"), list)


def _not_srd(client: httpx.Client) -> str:
    """The start of the message about a server that answers as no srd server does."""
    url = str(client.base_url).rstrip("/")
    return f"the server at {url} answered something that is not an srd auction"


def final_state(client: httpx.Client, auction_id: int) -> dict[str, Any]:
    """``GET /auctions/{id}`` once the stream has ended: the auction's final state."""
    final = client.get(f"/auctions/{auction_id}")
    if final.status_code != 200:
        raise WatchError(f"GET /auctions/{auction_id}: HTTP {final.status_code}")
    try:
        state = parsed(final.content, FINAL)
    except NotAnEventError as exc:
        raise WatchError(f"{_not_srd(client)}: GET /auctions/{auction_id}: {exc}") from None
    if state["id"] != auction_id:
        raise WatchError(
            f"{_not_srd(client)}: GET /auctions/{auction_id} answered auction {state['id']}"
        )
    return state


def server_option(ctx: click.Context, param: click.Parameter, value: str) -> str:
    """``--server`` as ``server_url`` reads it; a value from ``SRD_URL`` is named so."""
    try:
        return server_url(ctx, param, value)
    except (click.BadParameter, httpx.InvalidURL) as exc:  # InvalidURL: server_url's own fault
        message = str(exc.message if isinstance(exc, click.BadParameter) else exc)
        from_environment = ctx.get_parameter_source("server") == ParameterSource.ENVIRONMENT
        hint = "SRD_URL (for --server)" if from_environment else None
        raise click.BadParameter(message, ctx, param, param_hint=hint) from None


# --- what a person reads ------------------------------------------------------------------------


def price(value: float) -> str:
    """A price in the auction's money: three decimals (its steps are a few thousandths)."""
    return f"{value:.3f}"


def patrons(people: list[dict[str, Any]], with_price: bool = False) -> str:
    """``honest-1 v1 at 5.111, honest-3 v2``."""
    named = []
    for person in people:
        text = f"{person['participant']} v{person['version']}"
        if with_price:
            text += f" at {price(person['price'])}"
        named.append(text)
    return ", ".join(named)


def answers(round_event: dict[str, Any]) -> str:
    """How the patrons answered a fine-tuning round: ``4 accepted, 1 refused``."""
    counts = Counter(a["outcome"] for a in round_event.get("answers", []))
    nothing = "no answer yet" if round_event.get("status") == "open" else "no answers"
    return ", ".join(f"{n} {outcome}" for outcome, n in sorted(counts.items())) or nothing


def iteration_line(row: dict[str, Any]) -> str:
    votes = row["votes"]
    line = (
        f"iteration {row['iteration']}: price {price(row['price'])}, "
        f"fish {row['n_available']} -> {row['n_available_after']}, "
        f"votes buy {votes['buy']} hold {votes['hold']} quit {votes['quit']}"
    )
    if row.get("purchases"):
        line += f"; bought: {patrons(row['purchases'], with_price=True)}"
    if row.get("quits"):
        line += f"; quit: {patrons(row['quits'])}"
    return line


def round_line(data: dict[str, Any]) -> str:
    return (
        f"fine-tuning round {data['round']} (after iteration {data['iteration']}): "
        f"{data['status']}; {answers(data)}"
    )


def end_line(watched: Watched) -> str:
    end = watched.end or {}
    sold = sum(len(row.get("purchases", [])) for row in watched.iterations)
    revenue = sum(p["price"] for row in watched.iterations for p in row.get("purchases", []))
    line = (
        f"auction {watched.auction_id} {end.get('status')}"
        + (
            f" ({end['stop_reason']})"
            if end.get("stop_reason") not in (None, "", end.get("status"))  # not "cancelled" twice
            else ""
        )
        + f" after {end.get('iterations')} iteration{'' if end.get('iterations') == 1 else 's'}: "
        f"{end.get('n_sold', sold)} of "
        f"{end.get('n_initial')} fish sold, revenue {price(revenue)}, "
        + (  # the end's price is the one asked next, which no iteration asked
            f"price asked last {price(watched.iterations[-1]['price'])}"
            if watched.iterations
            else "no price asked"
        )
    )
    if end.get("error"):
        line += f"; error: {end['error']}"
    return line


def live_view(watched: Watched) -> Group:
    """The live table: where the auction stands, its latest iterations, its rounds."""
    last = watched.iterations[-1] if watched.iterations else None
    state = "ended" if watched.end else "running"
    head = Text(f"auction {watched.auction_id}: {state}", style="bold")
    if last is not None:
        head.append(
            f"   price {price(last['next_price'])}   supply: "
            f"{last['n_available_after']} fish left   iteration {last['iteration'] + 1}",
            style="",
        )
    table = Table("Iteration", "Price", "Fish left", "Buy", "Hold", "Quit", "Bought", "Quit by")
    for row in watched.iterations[-LIVE_ROWS:]:
        votes = row["votes"]
        table.add_row(
            str(row["iteration"]),
            price(row["price"]),
            f"{row['n_available']} -> {row['n_available_after']}",
            str(votes["buy"]),
            str(votes["hold"]),
            str(votes["quit"]),
            escape(patrons(row.get("purchases", []), with_price=True)),
            escape(patrons(row.get("quits", []))),
        )
    parts: list[Any] = [head, table]
    if watched.rounds:
        rounds = Table("Fine-tuning round", "After iteration", "Status", "Answers")
        for data in watched.rounds.values():
            rounds.add_row(  # the server's words are text, not markup
                str(data["round"]),
                str(data["iteration"]),
                escape(data["status"]),
                escape(answers(data)),
            )
        parts.append(rounds)
    return Group(*parts)


@click.command("watch")
@click.argument("auction_id", type=IntegerRange(1, MAX_AUCTION_ID))
@click.option(
    "--server",
    envvar="SRD_URL",
    default="http://127.0.0.1:8000",
    show_default=True,
    callback=server_option,
    help="Base URL of the auction house (or SRD_URL).",
)
@click.option(
    "--json", "json_output", is_flag=True, help="Print only the final state, as one JSON object."
)
@click.option(
    "--reconnect-s",
    type=FiniteRange(0, 86400),
    default=RECONNECT_S,
    show_default=True,
    help="How long a dropped stream is opened again before giving up (from its last event, "
    "or the last time it stayed open).",
)
def command(auction_id: int, server: str, json_output: bool, reconnect_s: float) -> None:
    """Follow one auction live: the price, the fish left (supply), each iteration's buy / hold /
    quit votes, who bought and who quit, and remote fine-tuning rounds, until the auction ends.
    Exit 0 when it finished, 1 when it failed or was cancelled, 2 for a bad option, 3 when it
    could not be followed (unreachable, unknown auction, the stream gone longer than
    --reconnect-s, a server that is not an srd server), 130 when interrupted (Ctrl-C). A
    dropped stream (a server restarting, its database away) is opened again, resuming after the
    last event."""
    err = Console(stderr=True, highlight=False, soft_wrap=True)
    out = Console(highlight=False, soft_wrap=True)
    watched = Watched(auction_id)

    def dropped(cause: str, pause: float) -> None:
        then = f"in {pause:g} s" if pause else "now"
        err.print(f"the event stream dropped ({escape(cause)}); opening it again {then}")

    try:
        with httpx.Client(base_url=server, timeout=TIMEOUT) as client:
            track = partial(follow, client, watched, reconnect_s=reconnect_s, dropped=dropped)
            if json_output:
                track(lambda name, data: None)
            elif out.is_terminal:
                with Live(live_view(watched), console=out, auto_refresh=False) as live:
                    track(lambda n, d: live.update(live_view(watched), refresh=True))
            else:
                track(_print_plain)
            final = final_state(client, auction_id) if json_output else None
    except (WatchError, httpx.HTTPError) as exc:
        err.print(f"[red]error:[/red] {escape(str(exc))}")
        if json_output:
            json_failure(str(exc))
        raise SystemExit(LOST) from exc
    if final is not None:
        sys.stdout.write(json.dumps(final) + "\n")
    else:
        out.print(escape(end_line(watched)))
    # the server ends the stream on any status but pending and running (finished, failed,
    # cancelled, or one added later): only a finished auction is a success
    status = (watched.end or {}).get("status")
    raise SystemExit(FINISHED if status == "finished" else ENDED_OTHERWISE)


def _print_plain(name: str, data: dict[str, Any]) -> None:
    if name == "iteration":
        click.echo(iteration_line(data))
    elif name == "round":
        click.echo(round_line(data))
