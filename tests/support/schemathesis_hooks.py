"""schemathesis hooks of test_schemathesis.py (loaded through ``SCHEMATHESIS_HOOKS``).

JSON Schema counts a number with a zero fraction (``411.0``) as an integer; the service, on
purpose, takes only integers written as integers where an integer goes (a strict reading of
JSON, refusing ``1.0`` for ``schema_version`` like ``"1"`` or ``true``). So generated bodies
write every whole number as an integer: the schema-valid data the service must accept, as it
states its inputs. A long poll's ``wait`` is cut to 1 s, so that the run's minutes go to
breadth (long polls are tested in test_remote_protocol.py). A study job's market options keep
the two rules across options that JSON Schema cannot state (refused with 422 naming the option,
tested in tests/studies/test_commands.py): a ``min_buy_price`` above ``base_price`` is sent as
``base_price``, a ``decrement`` above a fifth of ``increment`` as that fifth. A cheetah job
with a design ``stage`` is sent without the grid axes that stage does not take (it runs its
own conditions; refused with 422 naming the axis, tested in test_job_limits.py).
Everything else schemathesis generates goes out unchanged.
"""

from __future__ import annotations

import math
from typing import Any

import schemathesis

from sim.configs import GRID_AXES


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
    return _staged(_market_rules(_integers(body)))


def _staged(body: Any) -> Any:
    """A cheetah job's body with a design stage, less the grid axes that stage does not take."""
    if not isinstance(body, dict) or body.get("kind") != "cheetah":
        return body
    params = body.get("params")
    if not isinstance(params, dict):
        return body
    if not isinstance(params.get("stage"), int):
        return body
    ignored = ("inhibitor", "srd", "lr") if params["stage"] == 4 else GRID_AXES
    return {**body, "params": {k: v for k, v in params.items() if k not in ignored}}


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
    base, least = params.get("base_price", 5.0), params.get("min_buy_price")
    if _number(base) and _number(least) and least > base:
        fixed["min_buy_price"] = base
    increment, decrement = params.get("increment", 0.05), params.get("decrement")
    if _number(increment) and _number(decrement) and increment < 5 * decrement:
        fixed["decrement"] = increment / 5
    return {**body, "params": fixed}


def _number(value: Any) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)


@schemathesis.hook
def map_case(context: Any, case: Any) -> Any:
    """The coverage phase's cases too (``map_body`` is not applied to them)."""
    if isinstance(case.body, dict):
        case.body = _staged(_market_rules(case.body))
    return case
