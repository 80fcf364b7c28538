"""What every resource's bodies share: ids (in bodies and paths), strict input, a screener
finding, the health answers."""

from __future__ import annotations

from typing import Annotated, Any, Literal

from fastapi import Path
from pydantic import BaseModel, BeforeValidator, ConfigDict, Field
from pydantic_core import PydanticCustomError

from server.config import JobBackendName
from sim.experiment import JSON_NUMBER

MAX_SEED = 2**31 - 1  # fits a 32-bit INTEGER column on every backend
MAX_ROW_ID = 2**31 - 1  # ids are 32-bit INTEGER primary keys on every backend


def digits_only(value: Any) -> Any:
    """A path id or iteration is written in ASCII digits only: ``1.0``, ``1 `` or ``+1`` name
    no row (the bounds of each, from 1 or from 0, are the path parameter's)."""
    if isinstance(value, str) and not (value.isascii() and value.isdigit()):
        raise ValueError("must be a whole number written in digits, without a sign")
    return value


def decimal_only(value: Any) -> Any:
    """A number of seconds in a query is written as a JSON number: ``10``, ``2.5`` or
    ``1e-05``, not ``1_0``, `` 10``, ``+10`` or ``nan`` (which Python's ``float`` reads)."""
    if isinstance(value, str) and not (len(value) <= 32 and JSON_NUMBER.fullmatch(value)):
        raise ValueError("must be a number of seconds written as a JSON number, as 10 or 2.5")
    return value


def true_or_false(value: object) -> object:
    """A boolean query parameter is spelt ``true`` or ``false`` (pydantic would also read
    ``yes``, ``on``, ``1`` and their opposites)."""
    if isinstance(value, str) and value not in ("true", "false"):
        raise PydanticCustomError(
            "bool_parsing", "must be true or false, not {value}", {"value": repr(value[:64])}
        )
    return value


RowId = Annotated[int, Field(ge=1, le=MAX_ROW_ID)]
ModelIdPath = Annotated[
    int, Path(ge=1, le=MAX_ROW_ID, description="A model id."), BeforeValidator(digits_only)
]
AuctionIdPath = Annotated[
    int, Path(ge=1, le=MAX_ROW_ID, description="An auction id."), BeforeValidator(digits_only)
]
JobIdPath = Annotated[
    int, Path(ge=1, le=MAX_ROW_ID, description="A job id."), BeforeValidator(digits_only)
]
IterationPath = Annotated[
    int,
    Path(ge=0, le=MAX_ROW_ID, description="An auction iteration (0, 1, ...)."),
    BeforeValidator(digits_only),
]


class Schema(BaseModel):
    """Every request and response body of the API: a field's docstring is its description in
    the OpenAPI document (``/docs``, ``/openapi.json``)."""

    model_config = ConfigDict(use_attribute_docstrings=True)


class StrictInput(Schema):
    """A request body: unknown keys refused; numbers, booleans and integers typed strictly
    (``"3"``, ``true`` or ``3.0`` are not the integer 3)."""

    model_config = ConfigDict(extra="forbid", strict=True)


class HealthProblem(Schema):
    """Why the server is not ready: which check failed, and how."""

    check: Literal["database", "data_dir", "disk", "screener"]
    msg: str


class HealthPublic(Schema):
    """Readiness (``GET /healthz``): ``ok`` (200) or ``unavailable`` (503) with its problems."""

    status: Literal["ok", "unavailable"]
    problems: list[HealthProblem] = Field(default_factory=list)
    job_backend: JobBackendName
    """Where job units are computed (``SRD_JOB_BACKEND``)."""
    cpus: float
    """The CPUs that backend computes on: this machine's, or the Ray cluster's live nodes'."""
    screener_populations: str
    """The populations the screener's market-impact test meets: ``public``, or the marker of
    this server's ``SRD_SCREENER_SECRET`` (as each verdict's evidence names them)."""


class LivePublic(Schema):
    """Liveness (``GET /livez``): the process serves requests."""

    status: Literal["ok"]


class ReasonPublic(Schema):
    """A screener finding."""

    rule: str
    neuron: str
    message: str
