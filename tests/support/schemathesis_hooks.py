"""schemathesis hooks of test_schemathesis.py (loaded through ``SCHEMATHESIS_HOOKS``).

JSON Schema counts a number with a zero fraction (``411.0``) as an integer; the service, on
purpose, takes only integers written as integers where an integer goes (a strict reading of
JSON, refusing ``1.0`` for ``schema_version`` like ``"1"`` or ``true``). So generated bodies
write every whole number as an integer: the schema-valid data the service must accept, as it
states its inputs. A long poll's ``wait`` is cut to 1 s, so that the run's minutes go to
breadth (long polls are tested in test_remote_protocol.py). Everything else schemathesis
generates goes out unchanged.
"""

from __future__ import annotations

from typing import Any

import schemathesis


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
    return _integers(body)


@schemathesis.hook
def map_query(context: Any, query: Any) -> Any:
    if isinstance(query, dict) and isinstance(query.get("wait"), int | float):
        return {**query, "wait": min(query["wait"], 1)}
    return query
