"""Readiness (``GET /healthz``): can this server take writes now?

Four checks: the database takes writes (``Database.write_problem``: there, the one this
server started with, reachable, not read-only), a file can be written in the data folder, the
disks of the data folder and of a SQLite database have ``SRD_MIN_FREE_DISK_MB`` free, and the
screener judges (``ScreeningService.problem``: its process runs and answers). The
answer is kept ``CACHE_S``, so a flood of health checks costs one round of checks a second.
``/healthz`` is public: its problems name a folder by its role and setting, never its path.
"""

from __future__ import annotations

import os
import shutil
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from server.store.db import Database, is_sqlite, sqlite_path

CACHE_S = 1.0
"""How long a readiness answer is reused."""
MB = 1 << 20

Check = Literal["database", "data_dir", "disk", "screener"]

DATA_FOLDER = "the data folder (SRD_DATA_DIR)"
"""How public answers name the data folder (not by its path: where the server is installed)."""
DATABASE_FOLDER = "the SQLite database's folder (SRD_DATABASE_URL)"
"""How public answers name a SQLite database's folder."""


@dataclass(frozen=True)
class Problem:
    """A failed check: which one, and why."""

    check: Check
    msg: str


def data_dir_problem(path: Path, what: str | None = None) -> str | None:
    """Why files cannot be made in the folder ``path`` (``what``: how to name it; by default
    its path, for the operator starting the server), or None. A file is created, written
    and removed there: mode bits alone would not tell (root ignores them), a read-only mount,
    a full disk or a file in the folder's place would."""
    try:
        handle, name = tempfile.mkstemp(prefix=".srd-write-check-", dir=path)
        try:
            os.write(handle, b"srd")
        finally:
            os.close(handle)
            os.unlink(name)
    except OSError as exc:
        return f"{what or f'the data folder {path}'} cannot be written: {exc.strerror or exc}"
    return None


def _missing(path: Path) -> tuple[Path, list[Path]]:
    """``path`` made absolute and lexically normal (``a/../b`` is ``b``), and the folders of
    it that do not exist, outermost first (an error reading one: ``OSError``)."""
    normal = Path(os.path.abspath(path))
    missing: list[Path] = []
    for folder in (normal, *normal.parents):
        try:
            os.stat(folder)
        except (FileNotFoundError, NotADirectoryError):
            missing.insert(0, folder)
            continue
        break
    return normal, missing


def data_dir_unusable(path: Path) -> str | None:
    """Why the data folder ``path`` could not be made or written, or None, looked at without
    making it: when it is missing, its nearest existing parent must be a folder that can be
    written (a file is made and removed there)."""
    try:
        normal, missing = _missing(path)
    except OSError as exc:
        return f"the data folder {path} cannot be made: {exc.strerror or exc}"
    here = missing[0].parent if missing else normal
    if not here.is_dir():
        if here == normal:
            return f"the data folder {path} is a file, not a folder"
        return f"the data folder {path} cannot be made: {here} is a file, not a folder"
    problem = data_dir_problem(here)
    if problem is not None and missing:
        return f"the data folder {path} cannot be made: {problem}"
    return problem


def make_data_dir(path: Path) -> tuple[str | None, list[Path]]:
    """Make the data folder ``path`` if it is missing: why it cannot be made or written (or
    None), and the folders this made, for ``unmake_data_dir``."""
    made: list[Path] = []
    try:
        _, missing = _missing(path)
        for folder in missing:
            folder.mkdir()
            made.append(folder)
    except FileExistsError:
        return f"the data folder {path} is a file, not a folder", made
    except OSError as exc:
        return f"the data folder {path} cannot be made: {exc.strerror or exc}", made
    return data_dir_problem(path), made


def unmake_data_dir(made: list[Path]) -> None:
    """Remove the folders ``make_data_dir`` made, innermost first, while they are empty (a
    start refused after it leaves nothing behind)."""
    for folder in reversed(made):
        try:
            folder.rmdir()
        except OSError:  # something was put in it: it stays, and so do its parents
            return


def disk_problem(path: Path, min_free_mb: int, what: str) -> str | None:
    """Why the disk holding ``path`` (``what``: how to name it, not by its path: the
    answers that say it are public) is too full, or None."""
    found = disk_problem_kind(path, min_free_mb, what)
    return None if found is None else found[1]


def disk_problem_kind(path: Path, min_free_mb: int, what: str) -> tuple[str, str] | None:
    """``disk_problem`` with its kind: ``disk_full``, or ``disk_unreadable`` when the free
    space cannot be read (the folder gone, say)."""
    try:
        free_mb = shutil.disk_usage(path).free // MB
    except OSError as exc:
        why = f"the free space of {what} cannot be read: {exc.strerror or exc}"
        return "disk_unreadable", why
    if free_mb < min_free_mb:
        return "disk_full", (
            f"{free_mb} MB free on the disk of {what}, less than SRD_MIN_FREE_DISK_MB={min_free_mb}"
        )
    return None


class Readiness:
    """The checks of one server, with their answer cached ``CACHE_S``."""

    def __init__(
        self,
        database: Database,
        data_dir: Path,
        min_free_disk_mb: int,
        screener: Callable[[], str | None],
    ) -> None:
        self._database = database
        self._screener = screener
        self._data_dir = data_dir.resolve()
        self._min_free_mb = min_free_disk_mb
        self._folders = [(self._data_dir, DATA_FOLDER)]
        if is_sqlite(database.url):
            self._folders.append((sqlite_path(database.url).parent, DATABASE_FOLDER))
        self._lock = threading.Lock()
        self._problems: list[Problem] = []
        self._checked_at = -CACHE_S

    def cached(self) -> list[Problem] | None:
        """The last answer while it is fresh, else None (then ``check``: I/O, off the loop)."""
        with self._lock:
            fresh = time.monotonic() - self._checked_at <= CACHE_S
            return list(self._problems) if fresh else None

    def check(self) -> list[Problem]:
        """The problems now (none: ready); callers arriving meanwhile share the answer."""
        with self._lock:
            if time.monotonic() - self._checked_at > CACHE_S:
                self._problems = self._run()
                self._checked_at = time.monotonic()
            return list(self._problems)

    def _run(self) -> list[Problem]:
        problems: list[Problem] = []
        database = self._database.write_problem()
        if database is not None:
            problems.append(Problem("database", database))
        data_dir = data_dir_problem(self._data_dir, DATA_FOLDER)
        if data_dir is not None:
            problems.append(Problem("data_dir", data_dir))
        if self._min_free_mb > 0:
            for folder, what in dict(self._folders).items():
                disk = disk_problem(folder, self._min_free_mb, what)
                if disk is not None:
                    problems.append(Problem("disk", disk))
        screener = self._screener()
        if screener is not None:
            problems.append(Problem("screener", screener))
        return problems
