"""Bodies of jobs: ``POST /jobs``, ``GET /jobs/{id}``, the job list, the progress event."""

from __future__ import annotations

from datetime import datetime
from typing import Annotated, Any, Literal, get_args

from pydantic import Field, GetJsonSchemaHandler
from pydantic.json_schema import JsonSchemaValue
from pydantic_core import CoreSchema

from server.api.schemas.common import Schema, StrictInput
from server.store.status import JobStatus
from sim.experiment import config_schema
from studies.registry import KINDS

JobKind = Literal["fish", "lavaland", "cheetah", "auction-study", "comparison"]
assert set(get_args(JobKind)) == set(KINDS), "JobKind must list exactly the registry's kinds"


class JobCreate(StrictInput):
    """Start an experiment; ``params`` are the options of that kind (names with underscores or,
    as on the command line, dashes; lists as JSON arrays), checked by the kind's config."""

    kind: JobKind
    params: dict[str, Any] = Field(default_factory=dict)

    @classmethod
    def __get_pydantic_json_schema__(
        cls, core_schema: CoreSchema, handler: GetJsonSchemaHandler
    ) -> JsonSchemaValue:
        """One alternative per kind, its ``params`` the schema of the kind's config (bounds
        included), so the document says exactly what each kind accepts."""
        alternatives = [
            {
                "type": "object",
                "title": f"{name} job",
                "properties": {
                    "kind": {"const": name},
                    "params": config_schema(kind.config_class()),
                },
                "required": ["kind"],
                "additionalProperties": False,
            }
            for name, kind in KINDS.items()
        ]
        return {"title": "JobCreate", "description": cls.__doc__, "oneOf": alternatives}


class JobCreated(Schema):
    job_id: int
    status: JobStatus


class JobSummaryPublic(Schema):
    """A job as a list shows it (its result and error are on ``GET /jobs/{id}``)."""

    id: int
    kind: str
    status: JobStatus
    progress: Annotated[float, Field(ge=0, le=1)]
    message: str
    params: dict[str, Any]
    created_at: datetime
    started_at: datetime | None
    finished_at: datetime | None


class JobPublic(JobSummaryPublic):
    """A job; ``result`` is the CLI's ``--json`` object once it succeeded."""

    result: dict[str, Any] | None
    error: str | None
    artifacts: list[str]


class JobPage(Schema):
    items: list[JobSummaryPublic]
    next_cursor: int | None


class JobProgressEvent(Schema):
    """``event: progress``: the job's status, progress and message changed."""

    status: JobStatus
    progress: Annotated[float, Field(ge=0, le=1)]
    message: str
