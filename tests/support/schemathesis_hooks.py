"""schemathesis hooks of test_schemathesis.py (loaded through ``SCHEMATHESIS_HOOKS``).

JSON Schema counts a number with a zero fraction (``411.0``) as an integer; the service, on
purpose, takes only integers written as integers where an integer goes (a strict reading of
JSON, refusing ``1.0`` for ``schema_version`` like ``"1"`` or ``true``). So generated bodies
write every whole number as an integer: the schema-valid data the service must accept, as it
states its inputs. A long poll's ``wait`` is cut to 1 s, so that the run's minutes go to
breadth (long polls are tested in test_remote_protocol.py). A study job's market options keep
the two rules across options that JSON Schema cannot state (refused with 422 naming the option,
tested in tests/studies/test_commands.py): a ``min_buy_price`` above ``base_price`` is sent as
``base_price``, a ``decrement`` above a fifth of ``increment`` as an eighth of it (either given
or left to its default). A cheetah job
with a design ``stage`` is sent without the grid axes that stage does not take (it runs its
own conditions; refused with 422 naming the axis, tested in test_job_limits.py), and a cheetah
grid within its bounds on cells and runs (products of options). Text people
read (a manifest's ``description``, an appeal's or review's ``note``, an ``inspector``) goes
without the characters its schema ``pattern`` refuses: schemathesis drops that pattern (it
names a lone surrogate, for ECMA-262 engines that read UTF-16 units) and would otherwise
generate control characters the service refuses by name (tested in test_strict_input.py); a
note or inspector left blank by it is sent as ``x``. Everything else schemathesis generates
goes out unchanged.
"""

from __future__ import annotations

import math
import re
from dataclasses import fields
from typing import Any

import schemathesis

from agents.manifest import _LINE_BREAKS, _TAGS, _UNREADABLE
from sim.configs import (
    GRID_AXES,
    MAX_CELLS,
    MAX_RUNS,
    STAGE2_SWING_FROM,
    STAGE2_WINDOW,
    STAGE_ONLY_OF_GRID,
    CheetahConfig,
    LavalandConfig,
)
from studies.config import AuctionOptions

_REFUSED = {
    "description": re.compile(f"[{_UNREADABLE}{_TAGS}]"),
    "note": re.compile(f"[{_UNREADABLE}{_TAGS}]"),
    "inspector": re.compile(f"[{_UNREADABLE}{_LINE_BREAKS}{_TAGS}]"),
}
"""The characters each field of people's text refuses (``agents.manifest.PlainText``,
``PlainLine``)."""
EVAL_MAPS: int = LavalandConfig.eval_maps
"""Lavaland's evaluation maps when a job's params leave them out."""


def _integers(value: Any) -> Any:
    if isinstance(value, float) and value.is_integer() and abs(value) < 2**63:
        return int(value)
    if isinstance(value, dict):
        return {key: _integers(item) for key, item in value.items()}
    if isinstance(value, list):
        return [_integers(item) for item in value]
    return value


@schemathesis.hook
def map_body(context: Any, body: Any) -> Any:
    return _readable(_taken(_staged(_market_rules(_integers(body)))))


def _taken(body: Any) -> Any:
    """A job's body less the options its run would not take (each refused with 422 naming it:
    tests/studies/test_commands.py, tests/sim/test_cheetah.py): a study's fine-tuning options
    without fine-tuning (or 0 rounds with it: 1), a grid's 0 saboteurs; lavaland's training
    options with no training maps, and its ``gif_map`` taken modulo its evaluation maps (one
    past them is refused naming it, tests/server/test_job_limits.py); a cheetah grid's trials
    with nominal, its lr with SRD off."""
    params = body.get("params") if isinstance(body, dict) else None
    if not isinstance(params, dict):
        return body
    kind, fixed = body.get("kind"), dict(params)
    if kind in ("auction-study", "comparison"):
        if fixed.get("fine_tune") is True or fixed.get("grid") is True:
            if fixed.get("fine_tune_rounds") == 0:
                fixed["fine_tune_rounds"] = 1
        else:
            fixed.pop("fine_tune_rounds", None)
            fixed.pop("freeze_pfc", None)
        if fixed.get("grid") is True and fixed.get("saboteurs") == 0:
            fixed.pop("saboteurs")
    elif kind == "lavaland":
        if fixed.get("train_maps") == 0:
            for name in ("lr", "loss_guard", "srd_step"):
                fixed.pop(name, None)
        maps, gif_map = fixed.get("eval_maps", EVAL_MAPS), fixed.get("gif_map")
        if isinstance(maps, int) and isinstance(gif_map, int) and 0 < maps <= gif_map:
            fixed["gif_map"] = gif_map % maps
    elif kind == "cheetah" and not isinstance(fixed.get("stage"), int):
        if fixed.get("nominal") is True:
            fixed.pop("trials", None)
        if fixed.get("srd") == "off":
            fixed.pop("lr", None)
        _within_the_grid_bounds(fixed)
    return {**body, "params": fixed}


def _within_the_grid_bounds(params: dict[str, Any]) -> None:
    """A cheetah grid's cells (backswing × inhibitor × SRD variants) and runs (cells × trials)
    within ``MAX_CELLS`` and ``MAX_RUNS`` (a bound on a product, refused with 422 naming the
    option, tested in tests/sim/test_cheetah.py): fewer backswing values, then fewer trials."""
    defaults = {f.name: f.default for f in fields(CheetahConfig)}
    value = {name: params.get(name, defaults[name]) for name in (*GRID_AXES, "trials")}
    if not all(isinstance(value[n], list | tuple) for n in ("backswing", "inhibitor", "lr")):
        return
    srd = value["srd"]
    variants = (len(value["lr"]) if srd in ("on", "both") else 0) + (srd in ("off", "both"))
    per_backswing = max(1, len(value["inhibitor"]) * variants)
    if len(value["backswing"]) * per_backswing > MAX_CELLS:
        params["backswing"] = list(value["backswing"])[: max(1, MAX_CELLS // per_backswing)]
    cells = len(params.get("backswing", value["backswing"])) * per_backswing
    trials = value["trials"]
    if params.get("nominal") is not True and isinstance(trials, int) and cells * trials > MAX_RUNS:
        params["trials"] = max(1, MAX_RUNS // max(1, cells))


def _readable(value: Any) -> Any:
    """``value`` with its people's text (module docstring) as its schema's pattern reads."""
    if isinstance(value, list):
        return [_readable(item) for item in value]
    if not isinstance(value, dict):
        return value
    out = {}
    for key, item in value.items():
        if key in _REFUSED and isinstance(item, str):
            item = _REFUSED[key].sub("", item)
            if key != "description" and not item.strip():
                item = "x"
        out[key] = _readable(item)
    return out


def _staged(body: Any) -> Any:
    """A cheetah job's body with a design stage, less the grid axes and options that stage does
    not take (and the steps stage 2 needs at least)."""
    if not isinstance(body, dict) or body.get("kind") != "cheetah":
        return body
    params = body.get("params")
    if not isinstance(params, dict):
        return body
    if not isinstance(params.get("stage"), int):
        return body
    ignored = ("inhibitor", "srd", "lr") if params["stage"] == 4 else GRID_AXES
    ignored = (*ignored, *STAGE_ONLY_OF_GRID, "video")
    fixed = {k: v for k, v in params.items() if k not in ignored}
    least = STAGE2_SWING_FROM + STAGE2_WINDOW  # stage 2 swings and averages that long
    if params["stage"] == 2 and isinstance(fixed.get("steps"), int) and fixed["steps"] < least:
        fixed["steps"] = least
    return {**body, "params": fixed}


@schemathesis.hook
def map_query(context: Any, query: Any) -> Any:
    if isinstance(query, dict) and isinstance(query.get("wait"), int | float):
        return {**query, "wait": min(query["wait"], 1)}
    return query


def _market_rules(body: Any) -> Any:
    """A study job's body whose market options agree with each other (module docstring)."""
    params = body.get("params") if isinstance(body, dict) else None
    if not isinstance(params, dict):
        return body
    fixed = dict(params)
    base = params.get("base_price", AuctionOptions.base_price)
    least = params.get("min_buy_price", AuctionOptions.min_buy_price)  # given or not
    if _number(base) and _number(least) and least > base:
        fixed["min_buy_price"] = base
    increment = params.get("increment", AuctionOptions.increment)
    decrement = params.get("decrement", AuctionOptions.decrement)  # given or not
    if _number(increment) and _number(decrement) and increment < 5 * decrement:
        fixed["decrement"] = increment / 8  # below a fifth, however the division rounds
        if fixed["decrement"] <= 0:  # an increment too small to divide: the defaults
            fixed["increment"], fixed["decrement"] = (
                AuctionOptions.increment,
                AuctionOptions.decrement,
            )
    return {**body, "params": fixed}


def _number(value: Any) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)


@schemathesis.hook
def map_case(context: Any, case: Any) -> Any:
    """The coverage phase's cases too (``map_body`` is not applied to them)."""
    if isinstance(case.body, dict):
        case.body = _staged(_market_rules(case.body))
    return case
