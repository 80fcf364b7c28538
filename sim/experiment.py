"""Plumbing shared by every experiment: configs, output folders, progress reports, artifacts.

Every experiment module exposes a config dataclass (one field per option, each with a default,
bounds where it takes a number, and a one-line docstring) and ``run(config, *, out_dir,
progress) -> dict`` whose return value is the ``--json`` object of the CLI and the ``result`` of
a job. The CLI options and the job parameters are both generated from the dataclass
(``config_fields``, ``config_schema``) and validated by ``parse_config``; nothing restates them.

This module imports neither torch nor numpy: the command line reads configs without them.
"""

from __future__ import annotations

import ast
import csv
import dataclasses
import inspect
import itertools
import json
import math
import re
import textwrap
import threading
import time
import types
import typing
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, TypeVar

from pydantic import AfterValidator, TypeAdapter, ValidationError
from pydantic_core import PydanticCustomError

ProgressFn = Callable[[float, str], None]
"""Reports progress: a fraction in [0, 1] and a short human message."""

C = TypeVar("C")


def no_progress(fraction: float, message: str) -> None:
    """A progress callback that ignores its reports."""


def default_out_dir(command: str, seed: int, root: str | Path = "runs") -> Path:
    """``runs/<command>__<seed>__<YYYYmmdd-HHMMSS>/`` (local time), as CleanRL names its runs
    but readable, made here and now; a run that started in the same second with the same
    command and seed already made it, so this one takes ``...-2`` (``-3``, ...)."""
    base = Path(root) / f"{command}__{seed}__{time.strftime('%Y%m%d-%H%M%S')}"
    base.parent.mkdir(parents=True, exist_ok=True)
    for n in itertools.count(1):
        path = base if n == 1 else base.with_name(f"{base.name}-{n}")
        try:
            path.mkdir()
        except FileExistsError:
            continue
        return path
    raise AssertionError("unreachable")


def json_safe(value: Any) -> Any:
    """A JSON-ready copy: tuples become lists, numpy scalars plain numbers, NaN/inf null (a
    strict JSON reader refuses ``NaN``; the CLI's ``--json`` object and a job's result are the
    same)."""
    if isinstance(value, dict):
        return {str(key): json_safe(item) for key, item in value.items()}
    if isinstance(value, list | tuple):
        return [json_safe(item) for item in value]
    if hasattr(value, "item") and callable(value.item) and not isinstance(value, str):
        value = value.item()  # numpy / torch scalar
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if value is None or isinstance(value, bool | int | float | str):
        return value
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"result holds a {type(value).__name__}, which is not JSON")


def write_json(path: Path, obj: Any) -> None:
    """Write ``obj`` as indented strict JSON (``json_safe``; creating parent folders)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(json_safe(obj), indent=2, allow_nan=False) + "\n")


def write_csv(path: Path, rows: Sequence[dict[str, Any]]) -> str:
    """Write ``rows`` (dicts sharing their keys) as CSV with a header line, ``\\n`` line ends and
    empty cells for None; returns the file name. The one CSV writer of every experiment."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w", newline="") as handle:
        fields = list(rows[0]) if rows else []
        writer = csv.DictWriter(handle, fieldnames=fields, lineterminator="\n")
        writer.writeheader()
        writer.writerows({k: "" if v is None else v for k, v in row.items()} for row in rows)
    return path.name


def pyplot() -> Any:
    """matplotlib's pyplot on the file-only Agg backend, imported on first use (plots are the
    only part of an experiment that needs matplotlib)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


# --- Configs ----------------------------------------------------------------------------------


class ConfigError(ValueError):
    """A config field is invalid; ``errors`` holds ``{"field": ..., "message": ...}`` items."""

    def __init__(self, errors: list[dict[str, str]]) -> None:
        self.errors = errors
        super().__init__("; ".join(f"{e['field']}: {e['message']}" for e in errors))


@dataclass(frozen=True)
class ConfigField:
    """One option of an experiment, as the CLI and the job API present it."""

    name: str
    """The field name (job parameter); the CLI option is ``--`` + name with dashes."""
    kind: Literal["bool", "int", "float", "str", "choice", "list"]
    """How the value is typed in: a flag, a number, a word, one of ``choices``, a CSV list."""
    default: Any
    help: str
    """The field's docstring."""
    choices: tuple[str, ...] = ()
    item: Literal["int", "float", "str", "choice"] | None = None
    """For lists: the type of each item."""
    bounds: str = ""
    """The allowed range in words, e.g. ``1 ≤ x ≤ 65536`` (empty when unbounded)."""
    optional: bool = False
    """None is allowed (and means 'the experiment decides', see ``help``)."""
    max_items: int | None = None
    """For lists: the most values it takes (counted before any value is read)."""


def _attribute_docs(cls: type) -> dict[str, str]:
    """The docstrings written under the fields of ``cls`` and of its bases."""
    docs: dict[str, str] = {}
    for klass in reversed(cls.__mro__):
        if klass is object or not dataclasses.is_dataclass(klass):
            continue
        tree = ast.parse(textwrap.dedent(inspect.getsource(klass)))
        body = tree.body[0].body if isinstance(tree.body[0], ast.ClassDef) else []
        for node, after in itertools.pairwise(body):
            if (
                isinstance(node, ast.AnnAssign)
                and isinstance(node.target, ast.Name)
                and isinstance(after, ast.Expr)
                and isinstance(after.value, ast.Constant)
                and isinstance(after.value.value, str)
            ):
                docs[node.target.id] = " ".join(after.value.value.split())
    return docs


def _constraints(metadata: Sequence[Any]) -> typing.Iterator[Any]:
    """The single constraints of an ``Annotated`` hint's metadata (``Field`` holds several)."""
    for constraint in metadata:
        inner = getattr(constraint, "metadata", None)
        if isinstance(inner, list):
            yield from _constraints(inner)
        else:
            yield constraint


def _bounds(metadata: Sequence[Any]) -> str:
    """``Field(ge=..., le=...)`` constraints in words, e.g. ``≥ 1, ≤ 65536``."""
    words = []
    for constraint in _constraints(metadata):
        for attr, sign in (("ge", "≥"), ("gt", ">"), ("le", "≤"), ("lt", "<")):
            value = getattr(constraint, attr, None)
            if value is not None:
                words.append(f"{sign} {value if isinstance(value, int) else format(value, 'g')}")
    return ", ".join(words)


def _lengths(metadata: Sequence[Any]) -> tuple[int | None, int | None]:
    """``Field(min_length=..., max_length=...)`` of a list."""
    low = high = None
    for constraint in _constraints(metadata):
        low = getattr(constraint, "min_length", low)
        high = getattr(constraint, "max_length", high)
    return low, high


def _lengths_in_words(low: int | None, high: int | None) -> str:
    if low is None and high is None:
        return ""
    return f"{low or 0} to {high} values" if high is not None else f"at least {low} values"


def _scalar(hint: Any) -> tuple[str, tuple[str, ...], str]:
    """(kind, choices, bounds) of a non-list type hint."""
    metadata: Sequence[Any] = ()
    if typing.get_origin(hint) is typing.Annotated:
        hint, *metadata = typing.get_args(hint)
    if typing.get_origin(hint) is Literal:
        return "choice", tuple(str(v) for v in typing.get_args(hint)), ""
    for python_type, kind in ((bool, "bool"), (int, "int"), (float, "float"), (str, "str")):
        if hint is python_type:
            return kind, (), _bounds(metadata)
    raise TypeError(f"config fields must be bool, int, float, str, Literal or tuples: {hint}")


def config_fields(cls: type) -> tuple[ConfigField, ...]:
    """The options of the config dataclass ``cls``, in field order. Read once, under a lock:
    the server builds configs in several threads at once, and reading them parses source
    (``ast.parse``), which CPython 3.11 may fail in two threads at once ("AST constructor
    recursion depth mismatch": a 500 for a burst of ``POST /jobs`` on a fresh server)."""
    found = _FIELDS.get(cls)
    if found is None:
        with _FIELDS_LOCK:
            found = _FIELDS.get(cls)
            if found is None:
                found = _FIELDS[cls] = _read_fields(cls)
    return found


def _read_fields(cls: type) -> tuple[ConfigField, ...]:
    hints = typing.get_type_hints(cls, include_extras=True)
    docs = _attribute_docs(cls)
    fields = []
    for f in dataclasses.fields(cls):
        hint, optional = hints[f.name], False
        if typing.get_origin(hint) in (typing.Union, types.UnionType):
            members = [a for a in typing.get_args(hint) if a is not type(None)]
            hint, optional = members[0], True
        item = max_items = None
        outer: Sequence[Any] = ()
        if typing.get_origin(hint) is typing.Annotated and typing.get_origin(
            typing.get_args(hint)[0]
        ) in (tuple, list):
            hint, *outer = typing.get_args(hint)  # bounds on the list itself (its length)
        if typing.get_origin(hint) in (tuple, list):
            item_kind, choices, bounds = _scalar(typing.get_args(hint)[0])
            kind, item = "list", item_kind
            low, max_items = _lengths(outer)
            bounds = ", ".join(b for b in (bounds, _lengths_in_words(low, max_items)) if b)
        else:
            kind, choices, bounds = _scalar(hint)
        if f.name not in docs:
            raise TypeError(f"{cls.__name__}.{f.name} has no docstring")
        fields.append(
            ConfigField(
                name=f.name,
                kind=kind,  # type: ignore[arg-type]
                default=f.default,
                help=docs[f.name],
                choices=choices,
                item=item,  # type: ignore[arg-type]
                bounds=bounds,
                optional=optional,
                max_items=max_items,
            )
        )
    return tuple(fields)


def _adapter(cls: type) -> TypeAdapter[Any]:
    found = _ADAPTERS.get(cls)
    if found is None:
        found = _ADAPTERS[cls] = TypeAdapter(cls)
    return found


_FIELDS: dict[type, tuple[ConfigField, ...]] = {}
_FIELDS_LOCK = threading.Lock()
_ADAPTERS: dict[type, TypeAdapter[Any]] = {}
"""Per config class, read once."""


def config_schema(cls: type) -> dict[str, Any]:
    """The JSON Schema of the config's parameters (bounds included), each described by its
    docstring, unknown keys refused, and the rules across them its class states as JSON
    Schema (``SCHEMA_RULES``): what ``POST /jobs`` publishes per kind."""
    schema = _adapter(cls).json_schema()
    for field in config_fields(cls):
        prop = schema["properties"][field.name]
        if field.kind == "list" and "items" in prop:  # a list, or one value (``_split_list``)
            listed = {k: v for k, v in prop.items() if k not in ("default", "title")}
            prop = schema["properties"][field.name] = {
                "anyOf": [listed, prop["items"]],
                **{k: prop[k] for k in ("default", "title") if k in prop},
            }
        prop["description"] = field.help
    schema["additionalProperties"] = False
    schema["description"] = " ".join((cls.__doc__ or "").split())
    rules = getattr(cls, "SCHEMA_RULES", ())
    if rules:  # rules across options that the config's ``problems`` checks, as JSON Schema
        schema["allOf"] = list(rules)
    return schema


def distinct(
    what: str, hint: str, key: Callable[[Any], Any] | None = None, apart: str = ""
) -> AfterValidator:
    """A list option's validator: each value once (a repeated one would count its runs twice
    in one cell's statistics); ``what`` names a value, ``hint`` says what to do instead.
    ``key``: what tells two values apart (two values of one key are one value given twice),
    which ``apart`` says in words."""

    def check(values: tuple[Any, ...]) -> tuple[Any, ...]:
        seen: dict[Any, Any] = {}
        for value in values:
            known = value if key is None else key(value)
            if known in seen:
                first = seen[known]
                if value == first:
                    template = "{value} is given twice: each {what} once ({hint})"
                    shown = f"{value:g}"
                else:
                    template = "{value} are one {what}{apart}: each {what} once ({hint})"
                    shown = f"{first!r} and {value!r}"
                raise PydanticCustomError(
                    "duplicate_value",
                    template,
                    {"value": shown, "what": what, "hint": hint, "apart": apart},
                )
            seen[known] = value
        return values

    return AfterValidator(check)


def _too_many(field: ConfigField, value: Any) -> str | None:
    """Why a list field's value holds more values than its bound, counted before any is read
    (a comma-separated string by its commas), or None."""
    if isinstance(value, str):
        count = value.count(",") + 1
    elif isinstance(value, list):
        count = len(value)
    else:
        return None
    if field.max_items is None or count <= field.max_items:
        return None
    return f"{count} values: at most {field.max_items}"


JSON_NUMBER = re.compile(r"-?(?:0|[1-9][0-9]*)(?:\.[0-9]+)?(?:[eE][-+]?[0-9]+)?")
TYPED_NUMBER = re.compile(r"[-+]?(?:[0-9]+(?:\.[0-9]*)?|\.[0-9]+)(?:[eE][-+]?[0-9]+)?")
"""A list item's number as a command line spells it: a JSON number, or as a single-value
option takes it (``.5``, ``5.``, ``+1``, ``007``); no ``inf``, ``nan``, hex or ``1_0``."""
TYPED_INTEGER = re.compile(r"[-+]?[0-9]+")
MAX_NUMBER_CHARS = 64
"""A longer item of a numeric list is not read as a number (any option's bounds are far
shorter to write): the validator names it."""


def _split_list(field: ConfigField, value: Any) -> Any:
    """A list field's value as the command line spells it: a comma-separated string ("0.1,0.5")
    gives its items, each read as a number as typed (``TYPED_NUMBER``: ".5" too) for numeric
    lists; a single number or word
    gives a list of one; any other value, and an empty item ("0.1,,0.5"), is left for the
    validator to name."""
    if isinstance(value, int | float) and not isinstance(value, bool):
        return [value]
    if not isinstance(value, str):
        return value
    parts = [part.strip() for part in value.split(",")]  # an empty item is the validator's
    if field.item not in ("int", "float"):
        return parts
    # a word that is not a number is left for the validator to name
    return [part if (number := read_number(part)) is None else number for part in parts]


def read_number(text: str) -> int | float | None:
    """``text`` as a number as typed (``TYPED_NUMBER``: an int, or a float: "1e400" is inf,
    refused later as not finite), or None when it is not one or is longer than
    ``MAX_NUMBER_CHARS``."""
    if len(text) > MAX_NUMBER_CHARS or not TYPED_NUMBER.fullmatch(text):
        return None
    return int(text) if TYPED_INTEGER.fullmatch(text) else float(text)


def _non_finite(value: Any, path: tuple[str | int, ...]) -> list[tuple[str | int, ...]]:
    """Where NaN or ±inf hide in decoded JSON (Python's parser lets them through)."""
    if isinstance(value, float) and not math.isfinite(value):
        return [path]
    if isinstance(value, dict):
        return [p for key, item in value.items() for p in _non_finite(item, (*path, key))]
    if isinstance(value, list | tuple):
        return [p for i, item in enumerate(value) for p in _non_finite(item, (*path, i))]
    return []


def parse_config(cls: type[C], params: Any, given: frozenset[str] | None = None) -> C:
    """Build the config dataclass ``cls`` from JSON-like ``params``, strictly.

    Keys may use dashes or underscores (``train-maps`` or ``train_maps``), and a flag its
    command line negation (``"no-srd": true`` is ``"srd": false``). Values are checked as JSON
    would type them: a number must be a number (not ``"3"``), a flag a boolean, integers
    integral; NaN and ±inf are refused; so are unknown keys. A list takes a JSON array, a
    comma-separated string as on the command line (``"0.1,0.5"``, its items read as JSON
    numbers where numbers are due) or a single value; one with more values than its bound is
    refused on their count alone, before any is read. Every problem is reported with the field
    it concerns. Options the config's ``problems`` reads as given (options that change nothing
    in this run are refused when given): ``given``, default every key of ``params``; a config
    stored whole (every field) is read back with ``given`` empty.
    """
    if not isinstance(params, dict):
        raise ConfigError([{"field": "params", "message": "must be a JSON object"}])
    fields = {f.name: f for f in config_fields(cls)}
    clean: dict[str, Any] = {}
    errors: list[dict[str, str]] = []
    for key, value in params.items():
        name = str(key).replace("-", "_")
        flag = fields.get(name.removeprefix("no_"))
        if name not in fields and flag is not None and flag.kind == "bool":
            if not isinstance(value, bool):  # named as sent, not as the flag it negates
                errors.append({"field": str(key), "message": "must be true or false"})
                continue
            name, value = flag.name, not value
        if name not in fields:
            errors.append(
                {"field": str(key), "message": f"unknown option; known: {sorted(fields)}"}
            )
        elif name in clean:
            errors.append({"field": str(key), "message": "given twice (spelt two ways)"})
        elif fields[name].kind == "list" and (too_many := _too_many(fields[name], value)):
            errors.append({"field": name, "message": too_many})
            clean[name] = None  # its values are not read
        else:
            is_list = fields[name].kind == "list"
            clean[name] = _split_list(fields[name], value) if is_list else value
    for path in _non_finite(clean, ()):
        errors.append(
            {"field": ".".join(str(p) for p in path), "message": "must be a finite number"}
        )
    if errors:
        raise ConfigError(errors)
    try:
        config: C = _adapter(cls).validate_json(json.dumps(clean), strict=True)
    except ValidationError as exc:
        raise ConfigError(
            [
                {"field": ".".join(str(p) for p in err["loc"]) or "params", "message": err["msg"]}
                for err in _first_causes(exc.errors())
            ]
        ) from exc
    problems = getattr(config, "problems", None)  # what no single option's type can say
    named = frozenset(clean) if given is None else given
    if problems is not None and (found := problems(named)):
        raise ConfigError(found)
    settled = getattr(config, "settled", None)  # defaults that depend on what was given
    if given is None and settled is not None:  # (a config stored whole is settled already)
        config = settled(named)
    return config


def _first_causes(errors: list[Any]) -> list[Any]:
    """Pydantic's errors without the length errors its item errors cause: a list whose items
    all failed is also "too short" (it counts the items that passed), which only confuses."""
    inner = {tuple(err["loc"][:-1]) for err in errors if len(err["loc"]) > 1}
    return [
        err
        for err in errors
        if not (err["type"] in ("too_short", "too_long") and tuple(err["loc"]) in inner)
    ]


@dataclass(frozen=True)
class Cost:
    """What an experiment's options ask of the machine, estimated before it runs."""

    seconds: float
    """Compute on one core (a conservative estimate from measured per-unit costs)."""
    option: str
    """The integer option that drives the cost most: the one to lower."""


def over_budget(
    config: Any, budget_s: float, setting: str = "SRD_JOB_BUDGET_S"
) -> ConfigError | None:
    """A ConfigError naming the option to lower when ``config.cost()`` exceeds ``budget_s``,
    with the largest value of that option that fits (the other options as given); ``setting``
    names where the budget comes from."""
    cost: Cost = config.cost()
    if cost.seconds <= budget_s:
        return None
    low, high = 0, int(getattr(config, cost.option))
    while high - low > 1:  # the largest value that fits, by bisection (cost grows with it)
        middle = (low + high) // 2
        fits = dataclasses.replace(config, **{cost.option: middle}).cost().seconds <= budget_s
        low, high = (middle, high) if fits else (low, middle)
    said = f"this run needs about {cost.seconds:.3g} s of compute, over the budget of "
    said += f"{budget_s:g} s ({setting})"
    if low >= 1:
        return ConfigError([{"field": cost.option, "message": f"{said}: lower {cost.option} to "
                             f"at most {low}"}])  # fmt: skip
    # Even its least value does not fit: the other options make each unit too dear, and the
    # error is the options' as a whole (an empty field: ``params`` itself), not this one's.
    least = dataclasses.replace(config, **{cost.option: 1}).cost().seconds
    return ConfigError(
        [
            {
                "field": "",
                "message": f"{said}, and about {least:.3g} s with {cost.option} 1: lower the "
                "options that make each of them dearer",
            }
        ]
    )


def config_dict(config: Any) -> dict[str, Any]:
    """The config as a JSON-ready dict (tuples become lists)."""
    result: dict[str, Any] = json.loads(json.dumps(dataclasses.asdict(config)))
    return result


class Stopwatch:
    """Wall-clock timer: ``elapsed_s`` in the result objects."""

    def __init__(self) -> None:
        self.start = time.perf_counter()

    def elapsed(self) -> float:
        return round(time.perf_counter() - self.start, 3)
