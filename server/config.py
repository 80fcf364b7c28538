"""Service settings: the one place that reads the environment (prefix ``SRD_``) and the
secret files (``SRD_SECRETS_DIR``)."""

from __future__ import annotations

import ipaddress
import os
import re
import unicodedata
from functools import lru_cache
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import (
    AliasChoices,
    Field,
    SecretStr,
    ValidationError,
    field_validator,
    model_validator,
)
from pydantic_settings import BaseSettings, SettingsConfigDict
from pydantic_settings import SettingsError as SourceError

JobBackendName = Literal["local", "ray"]
"""Where job units are computed."""


SCREENER_SECRET_LENGTH = 32
"""The fewest characters of ``SRD_SCREENER_SECRET`` (``openssl rand -hex 32`` gives 64)."""
SCREENER_SECRET_SYMBOLS = 10
"""The fewest different characters of ``SRD_SCREENER_SECRET`` (a random hex string of 32 has
about 14)."""


class Settings(BaseSettings):
    """Every knob of the auction house; each can be set as ``SRD_<NAME>`` in the environment."""

    # An empty variable (``SRD_AUCTION_WORKERS=``, as compose's ``${VAR:-}`` gives) is unset.
    model_config = SettingsConfigDict(
        env_prefix="SRD_", extra="ignore", env_ignore_empty=True, allow_inf_nan=False
    )

    database_url: str = "sqlite:///./srd.db"
    """SQLAlchemy URL; SQLite (WAL mode) by default, ``postgresql+psycopg://...`` works too."""
    data_dir: Path = Path("./data")
    """Job artifacts (``jobs/<id>/``) and the generated admin token file live here."""
    min_free_disk_mb: Annotated[int, Field(ge=0)] = 256
    """``/healthz`` answers 503 when the disk of the data folder (or of a SQLite database's
    folder) has less free space than this (MB; 0: no check)."""
    admin_token: SecretStr | None = None
    """Operator token; when unset one is generated at first start into ``admin_token_file``."""
    screener_secret: SecretStr | None = None
    """A deployment's secret for the screener's market-impact test: its reference populations
    and test auctions are drawn from it too, so that a model tuned offline against the public
    screener meets populations it never saw. Every replica needs the same one. The app hands it
    to the screening and worker processes it starts, through their environment
    (``server.services``, ``screener.secret.SECRET_VARIABLE``)."""
    max_body_bytes: Annotated[int, Field(ge=1024)] = 262_144
    """Request bodies larger than this are refused with 413."""
    auction_workers: Annotated[int, Field(ge=1, le=64)] | None = None
    """Worker processes that run the steps of every auction (default: one per core). How many
    auctions are live at once is not bounded by it: an open round holds no process."""
    job_workers: Annotated[int, Field(ge=1, le=64)] = 1
    """Jobs run at the same time, each in its own worker process."""
    worker_torch_threads: Annotated[int, Field(ge=1, le=256)] = 1
    """Torch threads per auction/job worker process (the API keeps the remaining cores)."""
    worker_nice: Annotated[int, Field(ge=0, le=19)] = 10
    """Scheduling niceness added to job worker processes (POSIX ``nice``): experiments yield
    the CPU to the API's requests under load, and take it all when idle. Auction step workers
    run at the API's priority: a step is short, and the next round waits for it."""
    job_timeout_s: Annotated[float, Field(gt=0, le=7 * 86400)] = 3600.0
    """Wall-time limit of one job: a job still running after this long is stopped and failed."""
    job_memory_mb: Annotated[int, Field(ge=1536, le=1 << 20)] = 4096
    """Address-space limit of a job's worker process (MB, ``RLIMIT_AS``, enforced by the OS;
    with the ``ray`` job backend a limit on its data, ``RLIMIT_DATA``, as Ray maps its shared
    object store into the process). At least 1536: a worker forked with torch loaded already
    maps about 700 MB, and every job kind's defaults run within 1536 (a default lavaland job
    fails within 1024)."""
    job_disk_mb: Annotated[float, Field(gt=0, le=1 << 30)] = 1024
    """Disk a job's folder may take (MB): a job whose files grow past it is stopped at its
    next progress report, or at its end, and failed saying so, its files removed. A job starts
    only while the data folder's disk has ``min_free_disk_mb`` free."""
    job_budget_s: Annotated[float, Field(gt=0, le=1e12)] = 1800.0
    """Jobs whose estimated compute (seconds on one core) exceeds this are refused with 422."""
    max_queued_jobs: Annotated[int, Field(ge=1, le=100_000)] = 64
    """Jobs waiting to run at most: past it ``POST /jobs`` is answered 503 with
    ``Retry-After`` (``JOB_QUEUE_RETRY_AFTER_S``) until some have started."""
    max_live_auctions: Annotated[int, Field(ge=1, le=1_000_000)] = 256
    """Auctions pending or running at most: past it ``POST /auctions`` is answered 503 with
    ``Retry-After`` until some have ended (each live auction holds its rows and, while it
    plays, a worker's time)."""
    auction_timeout_s: Annotated[float, Field(gt=0, le=7 * 86400)] = 3600.0
    """Wall-time limit of one auction step (iterations played until the auction ends or opens
    a round): a step still running after this long is stopped and its auction failed."""
    quota_versions_per_minute: Annotated[int, Field(ge=1)] = 20
    """New accepted versions one participant may submit per minute."""
    quota_versions_per_day: Annotated[int, Field(ge=1)] = 500
    """New accepted versions one participant may submit per day."""
    quota_address_versions_per_minute: Annotated[int, Field(ge=1)] = 300
    """New accepted versions per minute from one client address, all its participants."""
    quota_address_versions_per_day: Annotated[int, Field(ge=1)] = 20_000
    """New accepted versions per day from one client address, all its participants."""
    quota_registrations_per_day: Annotated[int, Field(ge=1)] = 200
    """New participant names registered per day from one client address."""
    quota_address_refusals_per_hour: Annotated[int, Field(ge=1)] = 60
    """Screener refusals per hour from one client address, all its participants."""
    quota_address_appeals_per_day: Annotated[int, Field(ge=1)] = 10
    """Appeals per day from one client address, all its participants: each puts a refused
    model back in the inspectors' queue."""
    refusal_cooldown_s: Annotated[float, Field(ge=0, le=86400)] = 10.0
    """After a screener refusal a participant waits this long to submit again, doubled for each
    further refusal in a row (an accepted version resets it)."""
    refusal_cooldown_max_s: Annotated[float, Field(ge=0, le=86400)] = 3600.0
    """The longest refusal cooldown."""
    review_margin: Annotated[float, Field(ge=0, le=1)] = 0.005
    """Price units: a verdict whose deciding evidence lies strictly within this of its bar is
    held for an inspector (``screener.review``); 0 turns review off."""
    progress_interval_s: Annotated[float, Field(gt=0)] = 0.5
    """Minimum time between two progress writes of a running job."""
    event_poll_interval_s: Annotated[float, Field(gt=0, le=10)] = 0.05
    """On SQLite, how often the watched auctions and jobs are read while an event stream, a long
    poll or a round socket listens, if anything was committed since the last read (one query
    for all the watched auctions, one for all the watched jobs, per interval; whatever the
    number of listeners)."""
    live_safety_poll_s: Annotated[float, Field(gt=0, le=3600)] = 5.0
    """On PostgreSQL, where commits announce changes (``NOTIFY``), how often the watched rows
    are read anyway (a safety net)."""
    event_keepalive_s: Annotated[float, Field(gt=0, le=300)] = 15.0
    """An idle event stream sends a comment this often (proxies keep it open, and a client that
    went away is noticed)."""
    max_event_streams: Annotated[int, Field(ge=1, le=100_000)] = 256
    """Event streams open at once in one process; more get 503 with ``Retry-After``."""
    lease_s: Annotated[float, Field(ge=1, le=3600)] = 10.0
    """How long a server's claim on an auction or job lasts unless renewed (every third of
    it): a replica that dies hands its work to another after at most this long (PostgreSQL;
    with SQLite one server holds everything)."""
    job_backend: JobBackendName = "local"
    """Where a job's units are computed: ``local`` (in the job's worker process) or ``ray``
    (as tasks on the Ray cluster at ``ray_address``; needs ``pip install '.[ray]'``)."""
    ray_address: str | None = Field(
        default=None,
        validation_alias=AliasChoices("SRD_RAY_ADDRESS", "RAY_ADDRESS", "ray_address"),
    )
    """The Ray cluster of ``job_backend=ray``: its head's ``host:port``, ``ray://host:port``
    (Ray Client) or ``auto`` (a cluster started on this machine by ``ray start``); read from
    ``SRD_RAY_ADDRESS``, else from Ray's own ``RAY_ADDRESS``."""
    ray_max_retries: Annotated[int, Field(ge=0, le=100)] = 3
    """Times a unit lost with its Ray worker or node is run again (units are idempotent)."""
    ray_join_timeout_s: Annotated[float, Field(gt=0, le=600)] = 30.0
    """How long the server's look at the Ray cluster (at start, then for ``/healthz``), and a
    job worker's look before it joins, may take: Ray itself waits forever for an address
    nobody answers on, or a head that takes the connection and never answers."""
    access_log: bool = True
    """Log every request (uvicorn's access log). Off behind a proxy that logs them: the log
    line costs the API a tenth to a quarter of its CPU for a small request."""
    limit_client_sockets: Annotated[int, Field(ge=1, le=100_000)] = 128
    """Round sockets one client address may hold open at once (an agent needs one; one host
    may run the 64 agents of an auction); more are refused with 429."""
    limit_client_streams: Annotated[int, Field(ge=1, le=100_000)] = 16
    """Event streams one client (participant token, else address) may hold open at once."""
    limit_client_long_polls: Annotated[int, Field(ge=1, le=100_000)] = 128
    """Waiting ``GET .../rounds/current?wait=S`` (S > 0) one client may hold at once (an agent
    needs one; agents that poll without a token share their host's address)."""
    limit_client_uploads: Annotated[int, Field(ge=1, le=100_000)] = 2
    """Uploads (round PUTs and socket uploads, ``POST /submit``) one participant token may have
    in flight."""
    limit_address_uploads: Annotated[int, Field(ge=1, le=100_000)] = 128
    """Uploads without a token (first ``POST /submit``) one address may have in flight."""
    limit_retry_after_s: Annotated[int, Field(ge=1, le=3600)] = 2
    """The ``Retry-After`` of a client over one of its limits."""
    limit_address_requests_per_s: Annotated[float, Field(gt=0, le=1e9)] = 100.0
    """Requests (WebSocket handshakes and round-socket messages too) one address may send a
    second, sustained; a burst of four seconds' worth passes at once. Beyond it, 429 with
    ``Retry-After``. The operator's token is not counted. (The compose deployment's proxy
    allows 20 a second per address in front of it.)"""
    header_timeout_s: Annotated[float, Field(gt=0, le=30)] = 10.0
    """``srd serve``: a connection must send a request's whole header this soon (from its
    first byte, or from connecting), else it is answered 408 and closed."""
    body_timeout_s: Annotated[float, Field(gt=0, le=600)] = 30.0
    """``srd serve``: a request's whole body must arrive this soon after its header."""
    send_timeout_s: Annotated[float, Field(gt=0, le=600)] = 30.0
    """``srd serve``: a connection whose peer reads nothing of an answer for this long (the
    server's send buffer full the whole time) is closed."""
    max_header_bytes: Annotated[int, Field(ge=4096, le=1 << 20)] = 65_536
    """``srd serve``: a request header larger than this is answered 431 and closed."""
    keep_alive_s: Annotated[float, Field(gt=0, le=300)] = 5.0
    """``srd serve``: an idle keep-alive connection is closed after this long."""
    max_connections: Annotated[int, Field(ge=16, le=1_000_000)] = 4096
    """``srd serve``: open connections (and requests in flight) past which a request is
    answered 503; never more than the file-descriptor limit leaves room for."""
    max_connections_per_address: Annotated[int, Field(ge=1, le=1_000_000)] = 512
    """``srd serve``: open HTTP connections one client address may hold (a trusted proxy's are
    not counted; round sockets count apart, ``limit_client_sockets``); past it a new
    connection is answered 429 and closed."""
    trusted_proxies: str = ""
    """Comma-separated addresses or networks (``10.0.0.0/8``) of the reverse proxies whose
    ``X-Forwarded-For`` / ``X-Forwarded-Proto`` name the client; empty: nobody's (a direct
    client cannot choose the address its quotas and limits count against)."""
    allowed_hosts: str = ""
    """Comma-separated host names (``auction.example.com``, ``*.example.com``) under which
    browsers' pages may send writes, besides IP addresses and ``localhost``; ``*``: any. A page
    at any other name that resolves to this server (DNS rebinding) is refused 403
    ``host_not_allowed``. Requests no page sent (scripts, ``srd``, a typed URL) are not
    concerned."""
    host: str = "127.0.0.1"
    """Address ``srd serve`` binds by default."""
    port: Annotated[int, Field(ge=0, le=65535)] = 8000
    """Port ``srd serve`` binds by default."""

    @field_validator("admin_token")
    @classmethod
    def _header_token(cls, value: SecretStr | None) -> SecretStr | None:
        """White space around it dropped (a secret file's line end); refused unless it can be
        presented: printable ASCII in an ``Authorization`` header."""
        if value is None:
            return None
        token = value.get_secret_value().strip()
        problem = token_problem(token)
        if problem is not None:
            raise ValueError(problem)
        return SecretStr(token)

    @field_validator("screener_secret")
    @classmethod
    def _random_secret(cls, value: SecretStr | None) -> SecretStr | None:
        """Normalised as the screener hashes it, and refused unless it looks drawn at random:
        evidence anyone may read fingerprints the populations, so a guessable secret can be
        found offline (docs/screener.md)."""
        if value is None:
            return None
        secret = unicodedata.normalize("NFC", value.get_secret_value().strip())
        try:
            secret.encode("utf-8")
        except UnicodeEncodeError:
            raise ValueError("a secret is text (UTF-8)") from None
        if len(secret) < SCREENER_SECRET_LENGTH or len(set(secret)) < SCREENER_SECRET_SYMBOLS:
            raise ValueError(
                f"a secret has at least {SCREENER_SECRET_LENGTH} characters, "
                f"{SCREENER_SECRET_SYMBOLS} of them different: draw one at random "
                "(openssl rand -hex 32)"
            )
        return SecretStr(secret)

    @field_validator("trusted_proxies")
    @classmethod
    def _proxy_addresses(cls, value: str) -> str:
        for entry in _split(value):
            try:
                ipaddress.ip_network(entry, strict=False)
            except ValueError as exc:
                raise ValueError(f"{entry!r} is not an IP address or network") from exc
        return value

    @field_validator("allowed_hosts")
    @classmethod
    def _host_names(cls, value: str) -> str:
        for entry in _split(value):
            if entry != "*" and HOST_PATTERN.fullmatch(entry) is None:
                raise ValueError(
                    f"{entry!r} is not a host name (letters, digits, '-' and '.', a leading "
                    "'*.' for every subdomain, or '*' for any; no scheme or port)"
                )
        return value.lower()

    @field_validator("host")
    @classmethod
    def _some_host(cls, value: str) -> str:
        problem = host_problem(value)
        if problem is not None:
            raise ValueError(problem)
        return value

    @model_validator(mode="after")
    def _ray_cluster_named(self) -> Settings:
        """``job_backend=ray`` names its cluster: without an address the server would start
        and fail its first job."""
        if self.job_backend == "ray" and not self.ray_address:
            raise ValueError(
                "SRD_JOB_BACKEND=ray needs SRD_RAY_ADDRESS: the Ray cluster's head host:port, "
                "ray://host:port, or auto (a cluster started on this machine by ray start)"
            )
        return self

    @property
    def trusted_proxy_list(self) -> list[str]:
        """``trusted_proxies`` as a list."""
        return _split(self.trusted_proxies)

    @property
    def allowed_host_names(self) -> tuple[str, ...]:
        """``allowed_hosts``, each entry once, lower case."""
        return tuple(dict.fromkeys(_split(self.allowed_hosts)))

    @property
    def admin_token_file(self) -> Path:
        """Where a generated admin token is kept (mode 0600)."""
        return self.data_dir / "admin_token"

    @property
    def databases_file(self) -> Path:
        """The databases this data folder has served (see ``server.store.db.prepare_database``)."""
        return self.data_dir / "databases.json"


OPERATOR_TOKEN = re.compile(r"[\x21-\x7e]{1,4096}")
"""An operator token as a client can present it: printable ASCII without white space."""
HOST_PATTERN = re.compile(r"(\*\.)?[a-z0-9-]{1,63}(\.[a-z0-9-]{1,63})*\.?", re.ASCII | re.I)
"""An ``allowed_hosts`` entry: a DNS name, ``*.`` before it for every name under it."""


def token_problem(token: str) -> str | None:
    """Why an operator token cannot be presented in an ``Authorization`` header, or None."""
    if not token:
        return "an operator token cannot be empty"
    if OPERATOR_TOKEN.fullmatch(token) is None:
        return (
            "an operator token is printable ASCII without white space, at most 4096 characters "
            "(it travels in an Authorization header)"
        )
    return None


def host_problem(host: str) -> str | None:
    """Why ``host`` is no address to bind (``srd serve --host``, ``SRD_HOST``), or None."""
    if not host.strip():
        return "a host name or address to bind cannot be empty or white space"
    return None


def _split(value: str) -> list[str]:
    return [entry.strip() for entry in value.split(",") if entry.strip()]


SECRETS_DIR_VARIABLE = "SRD_SECRETS_DIR"
"""Names a folder of secret files, one per setting, named as its variable in lower case
(``srd_admin_token``, ``srd_database_url``: what ``docker compose`` mounts in /run/secrets);
a variable set in the environment wins over its file."""


class SettingsError(ValueError):
    """Settings that cannot be used: one line per problem, each naming its variable."""


@lru_cache(maxsize=1)
def get_settings() -> Settings:
    """The settings of this process, read once from the environment (and the secret files of
    ``SRD_SECRETS_DIR``, if set). Raises ``SettingsError`` naming each variable at fault."""
    secrets = os.environ.get(SECRETS_DIR_VARIABLE) or None
    if secrets is not None and not Path(secrets).is_dir():
        raise SettingsError(f"{SECRETS_DIR_VARIABLE}={secrets}: no such folder of secret files")
    if secrets is not None:  # a folder where a secret file belongs would be passed over
        for name in Settings.model_fields:
            entry = Path(secrets) / f"srd_{name}"
            if entry.exists() and not entry.is_file():
                raise SettingsError(f"{SECRETS_DIR_VARIABLE}={secrets}: {entry.name} is not a file")
    try:
        return Settings(_secrets_dir=secrets)
    except ValidationError as exc:
        raise SettingsError("\n".join(_in_words(error) for error in exc.errors())) from None
    except SourceError as exc:  # a secret file that cannot be read as text
        cause = f": {exc.__cause__}" if exc.__cause__ is not None else ""
        raise SettingsError(f"{SECRETS_DIR_VARIABLE}={secrets}: {exc}{cause}") from None


def _in_words(error: Any) -> str:
    """One validation error as ``SRD_NAME=value: what is wrong`` (a secret's value unsaid)."""
    message = str(error["msg"]).removeprefix("Value error, ")  # a validator's own words
    if not error["loc"]:  # a rule over several settings: its message names them
        return message
    field = str(error["loc"][0])
    name = f"SRD_{field.upper()}"
    secret = field in ("admin_token", "database_url", "screener_secret")
    given = "" if secret or error.get("input") is None else f"={error['input']}"
    return f"{name}{given}: {message}"
