"""schemathesis hooks of test_schemathesis.py (loaded through ``SCHEMATHESIS_HOOKS``).

JSON Schema counts a number with a zero fraction (``411.0``) as an integer; the service, on
purpose, takes only integers written as integers where an integer goes (a strict reading of
JSON, refusing ``1.0`` for ``schema_version`` like ``"1"`` or ``true``). So generated bodies
write every whole number as an integer: the schema-valid data the service must accept, as it
states its inputs. A long poll's ``wait`` is cut to 1 s, so that the run's minutes go to
breadth (long polls are tested in test_remote_protocol.py). A study job whose supply puts no
fish on sale (``int(rarity × patrons)`` = 0, a rule across two options that JSON Schema cannot
state; refused with 422 naming ``rarities``, tested in test_job_limits.py) is sent with that
rarity raised to 1 / patrons. A cheetah job with a design ``stage`` is sent without the grid
axes that stage does not take (it runs its own conditions; refused with 422 naming the axis,
tested in test_job_limits.py).
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
    return _staged(_with_fish(_integers(body)))


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


def _with_fish(body: Any) -> Any:
    """A study job's body whose every supply puts a fish on sale: a rarity below 1 / patrons
    raised to it (repeats then left out, as each supply is given once)."""
    params = body.get("params") if isinstance(body, dict) else None
    if not isinstance(params, dict) or "rarities" not in params:
        return body
    patrons, rarities = params.get("patrons", 64), params["rarities"]
    listed = rarities.split(",") if isinstance(rarities, str) else rarities
    if not isinstance(patrons, int) or patrons < 1 or not isinstance(listed, list | int | float):
        return body
    try:
        values = [float(r) for r in (listed if isinstance(listed, list) else [listed])]
    except (TypeError, ValueError):
        return body  # not numbers: the schema's own refusal
    if not all(0 < v <= 1 for v in values) or all(int(v * patrons) >= 1 for v in values):
        return body
    least = 1 / patrons
    while int(least * patrons) < 1:  # 1 / 49 × 49 is a hair below 1
        least = math.nextafter(least, 2)
    raised = list(dict.fromkeys(max(v, least) for v in values))
    return {**body, "params": {**params, "rarities": raised}}


@schemathesis.hook
def map_case(context: Any, case: Any) -> Any:
    """The coverage phase's cases too (``map_body`` is not applied to them)."""
    if isinstance(case.body, dict):
        case.body = _staged(_with_fish(case.body))
    return case
