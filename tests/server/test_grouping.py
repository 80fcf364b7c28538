"""server.grouping: items queued from event loops are done on one thread in groups of at most
MAX_GROUP, in arrival order; a failure reaches every waiter of its group; a group commit that
hits a conflict is replayed item by item, so only the item at fault gets the conflict answer."""

from __future__ import annotations

import asyncio
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest
from sqlalchemy.exc import IntegrityError, OperationalError
from sqlalchemy.orm import Session

from server.db import Database, upgrade_schema
from server.grouping import MAX_GROUP, GroupWorker, GroupWriter, StoppingError


def test_groups_take_what_is_queued_in_arrival_order() -> None:
    groups: list[list[int]] = []

    def handle(items: list[int]) -> list[int]:
        groups.append(items)
        return [10 * item for item in items]

    worker: GroupWorker[int, int] = GroupWorker("test", handle, on_error=lambda exc: exc)
    n_items = MAX_GROUP + 6

    async def main() -> list[int]:
        futures = [worker.put(item) for item in range(n_items)]  # queued before the thread runs
        worker.start()
        return list(await asyncio.gather(*futures))

    try:
        results = asyncio.run(main())
    finally:
        worker.shutdown()
    assert results == [10 * item for item in range(n_items)]
    assert groups == [list(range(MAX_GROUP)), list(range(MAX_GROUP, n_items))]


def test_a_gap_gathers_items_that_trickle_in() -> None:
    """With ``gather_gap_s``, items that come one by one, each well within the gap of the one
    before, make one group; an item after a longer pause starts the next group."""
    groups: list[list[int]] = []

    def handle(items: list[int]) -> list[int]:
        groups.append(items)
        return items

    gap = 0.2
    worker: GroupWorker[int, int] = GroupWorker(
        "test", handle, on_error=lambda exc: exc, gather_gap_s=gap
    )
    worker.start()

    async def main() -> None:
        trickle = []
        for item in range(4):
            trickle.append(worker.put(item))
            await asyncio.sleep(gap / 10)
        await asyncio.gather(*trickle)
        await asyncio.sleep(gap * 2)
        await worker.put(99)

    try:
        asyncio.run(main())
    finally:
        worker.shutdown()
    assert groups == [[0, 1, 2, 3], [99]]


def test_failures_reach_every_waiter_and_the_thread_goes_on() -> None:
    def handle(items: list[int]) -> list[int | BaseException]:
        if 0 in items:
            raise RuntimeError("the whole group failed")
        return [KeyError(item) if item == 2 else item for item in items]

    worker: GroupWorker[int, int] = GroupWorker("test", handle, on_error=lambda exc: -1)

    async def main() -> tuple[list[int], list[int | BaseException]]:
        first = [worker.put(0), worker.put(1)]
        worker.start()
        failed = list(await asyncio.gather(*first))
        later = await asyncio.gather(worker.put(2), worker.put(3), return_exceptions=True)
        return failed, list(later)

    try:
        failed, later = asyncio.run(main())
    finally:
        worker.shutdown()
    assert failed == [-1, -1]
    assert isinstance(later[0], KeyError) and later[1] == 3


def test_shutdown_does_what_is_queued_then_takes_nothing_more() -> None:
    passes: list[int] = []
    done: list[int] = []

    def handle(items: list[int]) -> list[int]:
        done.extend(items)
        return items

    worker: GroupWorker[int, int] = GroupWorker(
        "test", handle, on_error=lambda exc: exc, after_pass=lambda: passes.append(len(done))
    )

    async def main() -> list[int]:
        futures = [worker.put(item) for item in range(3)]
        worker.start()
        worker.shutdown()
        with pytest.raises(StoppingError):
            worker.put(9)
        return list(await asyncio.gather(*futures))

    assert asyncio.run(main()) == [0, 1, 2]
    assert done == [0, 1, 2] and passes[-1] == 3


def test_after_pass_runs_while_idle() -> None:
    idle = threading.Event()
    worker: GroupWorker[int, int] = GroupWorker(
        "test", lambda items: items, on_error=lambda exc: exc, idle_s=0.01, after_pass=idle.set
    )
    worker.start()
    try:
        assert idle.wait(5.0)
    finally:
        worker.shutdown()


@pytest.fixture
def database(tmp_path: Path) -> Iterator[Database]:
    url = f"sqlite:///{tmp_path / 'grouping.db'}"
    upgrade_schema(url)
    db = Database(url)
    yield db
    db.close()


def _writer(database: Database, seen: list[list[str]]) -> GroupWriter[str, str]:
    def decide(session: Session, group: list[str]) -> list[str]:
        seen.append(group)
        if "taken" in group:
            raise IntegrityError("INSERT", {}, Exception("UNIQUE constraint failed"))
        if "down" in group:
            raise OperationalError("SELECT", {}, Exception("disk I/O error\nmore"))
        return [f"stored {item}" for item in group]

    return GroupWriter(
        "test",
        database,
        decide,
        conflict=lambda item: f"conflict {item}",
        unavailable=lambda exc: f"unavailable: {exc.__class__.__name__}",
        stopping="stopping",
    )


def _one_group(writer: GroupWriter[str, str], items: list[str]) -> list[str]:
    async def main() -> list[str]:
        tasks = [asyncio.create_task(writer.write(item)) for item in items]
        await asyncio.sleep(0)  # every task has queued its item
        writer.start()
        return list(await asyncio.gather(*tasks))

    try:
        return asyncio.run(main())
    finally:
        writer.shutdown()


def test_a_conflict_is_replayed_item_by_item(database: Database) -> None:
    seen: list[list[str]] = []
    writer = _writer(database, seen)
    assert _one_group(writer, ["a", "taken", "c"]) == ["stored a", "conflict taken", "stored c"]
    assert seen == [["a", "taken", "c"], ["a"], ["taken"], ["c"]]
    assert writer.groups == 2  # "a" and "c", each in its own transaction
    assert asyncio.run(writer.write("after")) == "stopping"


def test_a_database_failure_answers_the_whole_group(database: Database) -> None:
    seen: list[list[str]] = []
    writer = _writer(database, seen)
    answers = _one_group(writer, ["a", "down"])
    assert answers == ["unavailable: OperationalError"] * 2
    assert seen == [["a", "down"]] and writer.groups == 0
