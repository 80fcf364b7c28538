"""The remote fine-tuning protocol in-process: creating remote auctions, the long poll, uploads
(accepted, repeated, refused by the re-screening) and every refusal, each naming its field or
round with nothing stored."""

from __future__ import annotations

import json
import sqlite3
import threading
import time
from datetime import UTC, datetime, timedelta
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient
from sqlalchemy import create_engine, text

from agents.manifest import Manifest, parse_manifest
from agents.remote import RoundInfo, always_hold, faithful_fine_tune
from screener import screen
from server.api.routes.rounds import UPLOAD_MAX_BYTES
from server.auctions import patrons
from server.config import Settings
from server.live import rounds as watcher
from server.store import crud
from server.store import db as db_module
from server.store.db import is_sqlite, sqlite_path
from tests.support.factories import honest, unique
from tests.support.server import ADMIN, wait_for

ROUND_WAIT_S = 60.0
"""Long enough to wait for a worker to start and play an iteration."""
QUITTER_SEED = 308
"""With these 8 patrons (seeds 308..315) and auction seed 5, patron 1 quits in iteration 0."""


def bearer(token: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {token}"}


def submit(client: TestClient, manifests: list[dict[str, Any]]) -> list[tuple[int, str]]:
    """(model id, token) of each manifest."""
    out = []
    for manifest in manifests:
        answer = client.post("/submit", json=manifest)
        assert answer.status_code == 201, answer.text
        out.append((answer.json()["model_id"], answer.json()["token"]))
    return out


def open_round(client: TestClient, auction_id: int, after: int = 0) -> dict[str, Any]:
    """The auction's round above ``after`` once open (or the state when the auction ended)."""
    return wait_for(
        lambda: client.get(
            f"/auctions/{auction_id}/rounds/current", params={"wait": 5, "after": after}
        ).json(),
        lambda r: (
            (r["status"] == "open" and r["round"] > after)
            or r["auction_status"] not in ("pending", "running")
        ),
        ROUND_WAIT_S,
    )


def put(
    client: TestClient, auction_id: int, round_: int, model_id: int, body: bytes, token: str | None
) -> Any:
    headers = {"Content-Type": "application/json", **({} if token is None else bearer(token))}
    return client.put(
        f"/auctions/{auction_id}/rounds/{round_}/models/{model_id}", content=body, headers=headers
    )


def loc_of(response: Any) -> list[Any]:
    return [item["loc"] for item in response.json()["detail"]]


def moving(name: str, seed: int) -> dict[str, Any]:
    """An honest manifest that fine-tunes one epoch at the honest range's largest rate."""
    data = honest(name, seed)
    data["fine_tuning"] = {"epochs": 1, "batch_size": 8, "learning_rate": 1e-4}
    return data


def start_remote(
    client: TestClient, prefix: str, first_seed: int, n: int, **fields: Any
) -> tuple[int, list[dict[str, Any]], list[tuple[int, str]]]:
    """A remote auction of ``n`` fine-tuning honest patrons (seeds ``first_seed`` on) for one
    fish, with the auction ``fields`` given: its id, the manifests, (model id, token) of each
    patron."""
    manifests = [moving(unique(prefix), seed=first_seed + i) for i in range(n)]
    patrons = submit(client, manifests)
    body = {"n_fish": 1, "model_ids": [m for m, _ in patrons], "fine_tune_mode": "remote"}
    created = client.post("/auctions", json={**body, **fields}, headers=ADMIN)
    assert created.status_code == 201, created.text
    return created.json()["auction_id"], manifests, patrons


def remote_auction(client: TestClient, prefix: str, first_seed: int, seed: int) -> dict[str, Any]:
    """A remote auction (``seed``) of 8 fine-tuning honest patrons (seeds ``first_seed`` on),
    round 1 open for a minute: its id, manifests, (model id, token) of each patron, the open
    round's state."""
    auction_id, manifests, patrons = start_remote(
        client, prefix, first_seed, 8, round_deadline_s=60, seed=seed
    )
    state = open_round(client, auction_id)
    assert state["status"] == "open" and state["round"] == 1, state
    return {"id": auction_id, "manifests": manifests, "patrons": patrons, "state": state}


def first_asked_upload(remote: dict[str, Any]) -> tuple[int, int, str, Manifest]:
    """The first asked patron of ``remote``'s open round: the auction, its model id, its
    token and its faithful fine-tuning for the round."""
    state = remote["state"]
    position, (model_id, token) = next(
        (i, p) for i, p in enumerate(remote["patrons"]) if p[0] in state["asked"]
    )
    info = RoundInfo.from_state(state, position)
    upload = faithful_fine_tune(parse_manifest(remote["manifests"][position]), info)
    return remote["id"], model_id, token, upload


@pytest.fixture(scope="module")
def remote(client: TestClient) -> dict[str, Any]:
    """A remote auction of 8 fine-tuning honest patrons, round 1 open for a minute."""
    return remote_auction(client, "remote", QUITTER_SEED, seed=5)


def test_remote_auctions_are_validated(client: TestClient) -> None:
    ((model_id, _),) = submit(client, [honest(unique("valid"), seed=1)])
    base = {"n_fish": 1, "model_ids": [model_id]}
    cases = [
        ({"fine_tune_mode": "remote", "fine_tune": False}, ["body", "fine_tune"]),
        ({"fine_tune_mode": "remote", "round_deadline_s": 0.1}, ["body", "round_deadline_s"]),
        ({"fine_tune_mode": "remote", "round_deadline_s": 301}, ["body", "round_deadline_s"]),
        ({"round_deadline_s": 5}, ["body", "round_deadline_s"]),
        ({"fine_tune_mode": "remote", "fine_tune_rounds": 65}, ["body", "fine_tune_rounds"]),
        ({"fine_tune_mode": "remote", "fine_tune_rounds": 0}, ["body", "fine_tune_rounds"]),
        ({"fine_tune": True, "fine_tune_rounds": 0}, ["body", "fine_tune_rounds"]),
        ({"fine_tune_rounds": 10}, ["body", "fine_tune_rounds"]),
        ({"fine_tune": False, "fine_tune_rounds": 2}, ["body", "fine_tune_rounds"]),
        ({"fine_tune_mode": "elsewhere"}, ["body", "fine_tune_mode"]),
        ({"rows": 0}, ["body", "rows"]),
        ({"rows": 257}, ["body", "rows"]),
        ({"rows": "16"}, ["body", "rows"]),
    ]
    for extra, loc in cases:
        answer = client.post("/auctions", json={**base, **extra}, headers=ADMIN)
        assert answer.status_code == 422 and loc in loc_of(answer), (extra, answer.text)


def test_the_round_is_published_with_rows_seeds_and_asked_patrons(
    client: TestClient, remote: dict[str, Any]
) -> None:
    state = remote["state"]
    assert state["auction_status"] == "running" and state["fine_tune_mode"] == "remote"
    assert state["iteration"] == 0 and state["fine_tune_rounds"] == 4
    assert 0 < state["seconds_left"] <= 60
    rows = np.array(state["rows"])
    assert rows.shape == (64, 8) and np.all(rows[:, 0] == rows[0, 0])  # one price
    assert rows[0, 1:7].tolist() == [1.0, 1.0, 1.0, 0.5, 0.5, 0.5]  # the prototype fish
    assert 0 <= state["fine_tune_seed"] < 2**53 and 0 <= state["augmentation_seed"] < 2**53
    assert set(state["asked"]) <= {m for m, _ in remote["patrons"]} and state["asked"]
    # An open round answers at once, even with a long wait.
    started = time.monotonic()
    again = client.get(f"/auctions/{remote['id']}/rounds/current", params={"wait": 20}).json()
    assert time.monotonic() - started < 5 and again["round"] == 1
    assert client.get("/auctions/987654/rounds/current").status_code == 404
    bad_wait = client.get(f"/auctions/{remote['id']}/rounds/current", params={"wait": 31})
    assert bad_wait.status_code == 422 and ["query", "wait"] in loc_of(bad_wait)
    # An auction that does not fine-tune has no rounds, as GET /auctions/{id} says too.
    ids = [client.post("/submit", json=honest(unique("plain"), seed=s)).json()["model_id"]
           for s in (2, 3)]  # fmt: skip
    body = {"n_fish": 1, "model_ids": ids, "seed": 3}
    plain = client.post("/auctions", json=body, headers=ADMIN).json()["auction_id"]
    none = client.get(f"/auctions/{plain}/rounds/current").json()
    assert none["status"] == "none" and none["fine_tune_rounds"] is None, none
    assert client.get(f"/auctions/{plain}").json()["fine_tune_rounds"] is None


def test_a_long_poll_waits_for_a_newer_round_at_most_its_wait(
    client: TestClient, remote: dict[str, Any]
) -> None:
    started = time.monotonic()
    state = client.get(
        f"/auctions/{remote['id']}/rounds/current", params={"wait": 0.6, "after": 1}
    ).json()
    waited = time.monotonic() - started
    assert state["round"] == 1 and state["status"] == "open"
    assert 0.55 <= waited < 5


def test_waiters_are_bounded_and_the_patrons_have_their_own_share(
    client: TestClient, remote: dict[str, Any], monkeypatch: pytest.MonkeyPatch
) -> None:
    """Watchers (no token, or not the auction's) cannot take the patrons' long polls: each
    kind has its own bound per process."""
    ((_, outsider),) = submit(client, [honest(unique("outsider"), seed=2)])
    monkeypatch.setattr(watcher, "MAX_WATCHER_WAITERS", 1)
    monkeypatch.setattr(watcher, "MAX_WAITERS", 1)
    answers: list[int] = []
    url = f"/auctions/{remote['id']}/rounds/current"
    first = threading.Thread(
        target=lambda: answers.append(client.get(url, params={"wait": 4, "after": 1}).status_code)
    )
    first.start()
    time.sleep(0.5)
    refused = client.get(url, params={"wait": 1, "after": 1})
    stranger = client.get(  # a real participant, but not this auction's patron
        url, params={"wait": 1, "after": 1}, headers=bearer(outsider)
    )
    (_, token) = remote["patrons"][0]
    monkeypatch.setattr(watcher, "MAX_WAITERS", 5)
    monkeypatch.setattr(patrons, "MAX_PER_PATRON", 1)
    patron_answers: list[int] = []
    waiting = threading.Thread(
        target=lambda: patron_answers.append(
            client.get(url, params={"wait": 2, "after": 1}, headers=bearer(token)).status_code
        )
    )
    waiting.start()
    time.sleep(0.3)
    # One patron of one auction holds at most its share of the patrons' slots there.
    again = client.get(url, params={"wait": 1, "after": 1}, headers=bearer(token))
    waiting.join()
    first.join()
    assert answers == [200]
    for watcher_refused in (refused, stranger):
        assert watcher_refused.status_code == 503, watcher_refused.text
        assert watcher_refused.headers["Retry-After"] == "1"
        assert "watchers'" in watcher_refused.json()["detail"][0]["msg"]
    assert patron_answers == [200]  # waited in the patrons' share
    assert again.status_code == 503, again.text
    # It is told its own share is taken, not the watchers' (it sent a patron's token).
    (item,) = again.json()["detail"]
    assert "this participant holds 1 of the patrons' long polls" in item["msg"], item
    assert "watchers'" not in item["msg"]


def test_an_upload_that_is_not_an_object_is_refused_at_the_body(
    client: TestClient, remote: dict[str, Any]
) -> None:
    """JSON that is not an object is refused 422 at ``["body"]``, the manifest as a whole, as
    ``POST /submit`` refuses it (before: at ``["body", "$"]``)."""
    auction_id, model_id, token, _ = first_asked_upload(remote)
    for body in (b"[1, 2]", b'"x"', b"3"):
        answer = put(client, auction_id, 1, model_id, body, token)
        assert answer.status_code == 422 and loc_of(answer) == [["body"]], answer.text
        submitted = client.post(
            "/submit", content=body, headers={"Content-Type": "application/json"}
        )
        assert submitted.status_code == 422 and loc_of(submitted) == [["body"]], submitted.text


def test_a_bad_field_is_refused_with_the_type_post_submit_gives_it(
    client: TestClient, remote: dict[str, Any]
) -> None:
    """The same mistake gets the same answer at both doors: location, and the schema's error
    type (before: ``manifest`` for every field of an upload)."""
    auction_id, model_id, token, tuned = first_asked_upload(remote)
    for field, value in (("bias", "x"), ("bias", None), ("weights", None)):
        data = tuned.model_dump(mode="json")
        if value is None:
            del data["decision"]["B"][field]
        else:
            data["decision"]["B"][field] = value
        upload = put(client, auction_id, 1, model_id, _json(data), token)
        at_the_door = client.post(
            "/submit", content=_json(data), headers={"Authorization": f"Bearer {token}"}
        )
        assert upload.status_code == at_the_door.status_code == 422, upload.text
        assert upload.json()["detail"] == at_the_door.json()["detail"], upload.text
        (item,) = upload.json()["detail"]
        assert item["loc"] == ["body", "decision", "B", field] and item["type"] != "manifest"


def stored_versions(client: TestClient, participant: str) -> int:
    return len(client.get("/models", params={"participant": participant}).json()["items"])


def refused(response: Any, status: int, loc: list[Any], words: str) -> None:
    """The response is a refusal with this status, naming ``loc`` and saying ``words``."""
    assert response.status_code == status, response.text
    assert loc in loc_of(response), response.text
    assert words in response.text, response.text


def refuse_every_bad_upload(
    client: TestClient, remote: dict[str, Any], position: int, tuned: Manifest
) -> None:
    """Each wrong way to upload ``tuned`` for the patron at ``position`` is refused by name:
    token, path, round, size, body, a changed design, a patron not asked."""
    auction_id = remote["id"]
    model_id, token = remote["patrons"][position]
    name = tuned.participant
    _, other_token = next((m, t) for m, t in remote["patrons"] if m != model_id)
    good = tuned.model_dump_json().encode()
    refused(
        put(client, auction_id, 1, model_id, good, None), 401, ["header", "Authorization"], "token"
    )
    refused(
        put(client, auction_id, 1, model_id, good, other_token),
        403,
        ["header", "Authorization"],
        name,
    )
    refused(put(client, 987654, 1, model_id, good, token), 404, ["path", "auction_id"], "987654")
    refused(put(client, auction_id, 1, 987654, good, token), 404, ["path", "model_id"], "987654")
    ((stranger, stranger_token),) = submit(client, [honest(unique("stranger"), seed=2)])
    refused(
        put(client, auction_id, 1, stranger, good, stranger_token),
        404,
        ["path", "model_id"],
        "not a patron",
    )
    refused(
        put(client, auction_id, 2, model_id, good, token),
        409,
        ["path", "round"],
        "the current round is 1 (open)",
    )
    for who in (token, None):  # an empty body is refused as a body, before the token
        refused(put(client, auction_id, 1, model_id, b"", who), 422, ["body"], "empty")
    padded = good[:-1] + b" " * UPLOAD_MAX_BYTES + b"}"
    for oversized in (padded, b"x" * (UPLOAD_MAX_BYTES + 1)):  # JSON or not, its size first
        for who in (token, None):
            refused(
                put(client, auction_id, 1, model_id, oversized, who),
                413,
                ["header", "Content-Length"],
                f"an upload is at most {UPLOAD_MAX_BYTES} bytes",
            )
    chunked = client.put(  # no Content-Length: the body is counted as it comes
        f"/auctions/{auction_id}/rounds/1/models/{model_id}",
        content=iter([b"x" * 40_000, b"x" * 40_000]),
        headers={**bearer(token), "Content-Type": "application/json"},
    )
    refused(chunked, 413, ["body"], f"an upload is at most {UPLOAD_MAX_BYTES} bytes")
    data = tuned.model_dump(mode="json")
    del data["decision"]["B"]["bias"]
    refused(
        put(client, auction_id, 1, model_id, _json(data), token),
        422,
        ["body", "decision", "B", "bias"],
        "",
    )
    body = _json(tuned.model_dump(mode="json"))
    lone = body.replace(b'"description": "', b'"description": "\\ud800', 1)
    assert b"\\ud800" in lone  # a lone surrogate escape: JSON, but no text
    refused(put(client, auction_id, 1, model_id, lone, token), 422, ["body", "description"], "")
    renamed = tuned.model_copy(update={"participant": "someone-else"})
    refused(
        put(client, auction_id, 1, model_id, renamed.model_dump_json().encode(), token),
        422,
        ["body", "participant"],
        name,
    )
    redesigned = tuned.model_dump(mode="json")
    redesigned["augmentation"]["copies"] = 3
    refused(
        put(client, auction_id, 1, model_id, _json(redesigned), token),
        422,
        ["body", "augmentation", "copies"],
        "only weights and biases",
    )
    quitter, quitter_token = remote["patrons"][1]
    assert quitter in auction_quitters(client, auction_id)
    refused(
        put(client, auction_id, 1, quitter, good, quitter_token),
        409,
        ["path", "model_id"],
        "not asked in round 1",
    )


def test_upload_refusals_name_the_field_and_store_nothing(
    client: TestClient, remote: dict[str, Any]
) -> None:
    auction_id, state = remote["id"], remote["state"]
    # An honest one (even position: the next test switches the odd ones).
    position = next(
        p for p, (m, _) in enumerate(remote["patrons"]) if m in state["asked"] and p % 2 == 0
    )
    model_id, token = remote["patrons"][position]
    manifest = parse_manifest(remote["manifests"][position])
    name = manifest.participant
    other_model, other_token = next((m, t) for m, t in remote["patrons"] if m != model_id)
    tuned = faithful_fine_tune(manifest, RoundInfo.from_state(state, position))
    good = tuned.model_dump_json().encode()

    refuse_every_bad_upload(client, remote, position, tuned)
    # Nothing of these was stored: no version, no answer.
    assert stored_versions(client, name) == 1
    auction = client.get(f"/auctions/{auction_id}").json()
    assert [a for r in auction["fine_tuning"] for a in r["answers"]] == []
    # Now the real upload, its repeat, and a different second upload.
    first = put(client, auction_id, 1, model_id, good, token)
    assert first.status_code == 200, first.text
    answer = first.json()
    assert answer["accepted"] and answer["outcome"] == "accepted" and answer["version"] == 2
    assert answer["parent_id"] == model_id and answer["round"] == 1
    again = put(client, auction_id, 1, model_id, good, token)
    assert again.status_code == 200 and again.content == first.content
    other = tuned.model_copy(update={"description": "x"}).model_dump(mode="json")
    other["decision"]["B"]["bias"] += 1e-9
    other["description"] = manifest.description
    refused(
        put(client, auction_id, 1, model_id, _json(other), token),
        409,
        ["path", "round"],
        "one upload per round",
    )
    assert stored_versions(client, name) == 2
    version = client.get(f"/models/{answer['model_id']}").json()
    assert version["parent_id"] == model_id and version["auction_id"] == auction_id
    assert version["patron_id"] == model_id  # round 1: fine-tuned from its patron
    assert client.get(f"/models/{model_id}").json()["patron_id"] is None  # no upload
    assert version["round"] == 1 and version["version"] == 2 and version["accepted"]
    assert parse_manifest(version["manifest"]) == tuned
    assert client.get(f"/models/{model_id}").json()["auctions"][0] == auction_id
    # A server-mode auction has no rounds to upload to.
    server_mode = client.post(
        "/auctions", json={"n_fish": 1, "model_ids": [other_model]}, headers=ADMIN
    ).json()["auction_id"]
    refused(
        put(client, server_mode, 1, other_model, good, other_token),
        409,
        ["path", "auction_id"],
        "has no remote fine-tuning rounds",
    )


def test_a_frozen_judge_stays_as_it_was_admitted(client: TestClient) -> None:
    """A model whose judge is frozen (``pfc.trainable`` false) is never fine-tuned there, so
    an upload that moves a PFC weight or bias is refused 422 naming each, and nothing of it is
    stored; the faithful fine-tuning of the same patron (its judge untouched) is accepted."""
    manifests = [moving(unique("frozen-judge"), seed=QUITTER_SEED + i) for i in range(8)]
    for data in manifests:
        data["pfc"]["trainable"] = False
    patrons = submit(client, manifests)
    body = {"n_fish": 1, "model_ids": [m for m, _ in patrons], "fine_tune_mode": "remote"}
    created = client.post("/auctions", json={**body, "round_deadline_s": 60}, headers=ADMIN)
    assert created.status_code == 201, created.text
    remote = {"id": created.json()["auction_id"], "manifests": manifests, "patrons": patrons}
    remote["state"] = open_round(client, remote["id"])
    auction_id, model_id, token, tuned = first_asked_upload(remote)
    switched = tuned.model_dump(mode="json")
    switched["pfc"]["verdict"]["F"]["bias"] += 0.5
    switched["pfc"]["judgement"]["FQ"]["weights"]["Q"] = 3.0
    answer = put(client, auction_id, 1, model_id, _json(switched), token)
    assert answer.status_code == 422, answer.text
    assert loc_of(answer) == [
        ["body", "pfc", "judgement", "FQ", "weights", "Q"],
        ["body", "pfc", "verdict", "F", "bias"],
    ]
    assert "the judge is frozen (pfc.trainable is false)" in answer.text
    assert stored_versions(client, tuned.participant) == 1
    accepted = put(client, auction_id, 1, model_id, tuned.model_dump_json().encode(), token)
    assert accepted.status_code == 200 and accepted.json()["accepted"], accepted.text


def auction_quitters(client: TestClient, auction_id: int) -> list[int]:
    return list(client.get(f"/auctions/{auction_id}").json()["quitters"])


def _json(data: dict[str, Any]) -> bytes:
    return json.dumps(data).encode()


def test_the_bait_and_switch_is_refused_and_the_round_closes_when_all_answered(
    client: TestClient, remote: dict[str, Any]
) -> None:
    auction_id, state = remote["id"], remote["state"]
    answers = {}
    for position, (model_id, token) in enumerate(remote["patrons"]):
        if model_id not in state["asked"]:
            continue
        manifest = parse_manifest(remote["manifests"][position])
        info = RoundInfo.from_state(state, position)
        switch = position % 2 == 1
        upload = always_hold(manifest, info) if switch else faithful_fine_tune(manifest, info)
        answer = put(client, auction_id, 1, model_id, upload.model_dump_json().encode(), token)
        assert answer.status_code == 200, answer.text
        answers[model_id] = (switch, answer.json())
        # The verdict is the screener's on the upload itself (the bait-and-switch never passes).
        assert answer.json()["accepted"] == (screen(upload).accepted and not switch)
    assert any(not switch and answer["accepted"] for switch, answer in answers.values())
    for switch, answer in answers.values():
        if switch:
            assert answer["outcome"] == "refused" and answer["reasons"]
            assert answer["version"] == 1 and answer["uploaded_id"] is not None
            assert client.get(f"/models/{answer['uploaded_id']}").json()["accepted"] is False
    # Everyone answered: the last verdict closed the round (long before its minute is up),
    # before the step that plays on has run; then the next round opens.
    assert client.get(f"/auctions/{auction_id}").json()["fine_tuning"][0]["status"] == "closed"
    nxt = open_round(client, auction_id, after=1)
    auction = client.get(f"/auctions/{auction_id}").json()
    first = auction["fine_tuning"][0]
    assert first["status"] == "closed" and first["round"] == 1
    outcomes = {a["model_id"]: a for a in first["answers"]}
    for model_id, (_, answer) in answers.items():
        assert outcomes[model_id]["outcome"] == answer["outcome"]
        assert outcomes[model_id]["version"] == answer["version"]
    # Publishing's cost: the round's rows as JSON, once to every asked patron.
    rows = json.dumps(state["rows"], separators=(",", ":"))
    assert first["bytes_published"] == len(rows) * len(state["asked"])
    uploads = sum(a["bytes_in"] + a["bytes_out"] for a in first["answers"])
    assert first["bytes_total"] == first["bytes_published"] + uploads > first["bytes_published"]
    assert nxt["round"] == 2 and nxt["status"] == "open"
    assert first["closed_at"] <= auction["fine_tuning"][1]["opened_at"]
    # A vote is explained with the version that cast it: round 1's accepted uploads bid from
    # iteration 1 on.
    for model_id, (_, answer) in answers.items():
        votes = f"/auctions/{auction_id}/iterations/{{}}/votes/{model_id}"
        assert client.get(votes.format(0)).json()["version"] == 1
        cast = client.get(votes.format(1)).json()
        assert cast["version"] == answer["version"]
        # version_id names the stored version that voted, whose page shows that version
        assert client.get(f"/models/{cast['version_id']}").json()["version"] == answer["version"]


def test_buyers_and_quitters_are_named_with_the_version_that_bid(client: TestClient) -> None:
    auction_id, manifests, patrons = start_remote(
        client, "bidder", 500, 4, round_deadline_s=60, fine_tune_rounds=1, seed=3
    )
    state = open_round(client, auction_id)
    names = {
        model_id: client.get(f"/models/{model_id}").json()["participant"] for model_id, _ in patrons
    }

    def entry_of(model_id: int) -> dict[str, Any]:
        page = client.get(f"/participants/{names[model_id]}").json()
        [entry] = [e for e in page["auctions"] if e["auction_id"] == auction_id]
        return entry

    first = entry_of(patrons[0][0])  # on its participant's page, in play
    assert (first["outcome"], first["auction_status"]) == ("bidding", "running")
    assert first["bidding_model_id"] == first["model_id"] == patrons[0][0]
    uploaded = {}
    for position, (model_id, token) in enumerate(patrons):
        if model_id in state["asked"]:
            info = RoundInfo.from_state(state, position)
            tuned = faithful_fine_tune(parse_manifest(manifests[position]), info)
            answer = put(client, auction_id, 1, model_id, tuned.model_dump_json().encode(), token)
            assert answer.status_code == 200, answer.text
            uploaded[model_id] = answer.json()["version"]
    assert 2 in uploaded.values()
    auction = wait_for(
        lambda: client.get(f"/auctions/{auction_id}").json(),
        lambda a: a["status"] == "finished",
        ROUND_WAIT_S,
    )
    left = [*auction["buyers"], *auction["quitter_details"]]
    assert left and any(entry["iteration"] >= 1 for entry in left)
    for entry in left:
        position = auction["model_ids"].index(entry["model_id"])
        bidding = client.get(f"/models/{auction['current_model_ids'][position]}").json()
        assert entry["version"] == bidding["version"], entry
        assert entry["version_id"] == auction["current_model_ids"][position], entry
        if entry["iteration"] >= 1:  # after round 1: the upload's version, if one was accepted
            assert entry["version"] == uploaded.get(entry["model_id"], 1)
    # Each participant's page names the version that bid and how its patron left.
    outcomes = {b["model_id"]: "bought" for b in auction["buyers"]}
    outcomes |= {q["model_id"]: "quit" for q in auction["quitter_details"]}
    for position, (model_id, _) in enumerate(patrons):
        entry = entry_of(model_id)
        assert entry["bidding_model_id"] == auction["current_model_ids"][position]
        assert entry["outcome"] == outcomes.get(model_id, "stayed"), entry


def test_a_silent_round_closes_at_its_deadline_and_late_uploads_get_410(
    client: TestClient,
) -> None:
    auction_id, manifests, patrons = start_remote(
        client, "silent", 400, 3, round_deadline_s=0.5, fine_tune_rounds=1, seed=1
    )
    auction = wait_for(
        lambda: client.get(f"/auctions/{auction_id}").json(),
        lambda a: a["fine_tuning"] and a["fine_tuning"][0]["status"] == "closed",
        ROUND_WAIT_S,
    )
    closed = auction["fine_tuning"][0]
    took = _seconds(closed["closed_at"]) - _seconds(closed["opened_at"])
    assert 0.5 <= took < 5, closed
    asked = [a["model_id"] for a in closed["answers"]]
    assert asked and all(a["outcome"] == "missing" for a in closed["answers"])
    model_id = asked[0]
    position = [m for m, _ in patrons].index(model_id)
    body_bytes = parse_manifest(manifests[position]).model_dump_json().encode()
    late = put(client, auction_id, 1, model_id, body_bytes, patrons[position][1])
    assert late.status_code == 410 and ["path", "round"] in loc_of(late), late.text
    assert "round 1" in late.text
    auction = client.get(f"/auctions/{auction_id}").json()
    outcome = {a["model_id"]: a["outcome"] for a in auction["fine_tuning"][0]["answers"]}
    assert outcome[model_id] == "late"
    assert stored_versions(client, manifests[position]["participant"]) == 1
    # Once the auction has ended, an upload to a round past its last says so.
    ended = wait_for(
        lambda: client.get(f"/auctions/{auction_id}").json(),
        lambda a: a["status"] not in ("pending", "running"),
        ROUND_WAIT_S,
    )
    refused(
        put(client, auction_id, 2, model_id, body_bytes, patrons[position][1]),
        409,
        ["path", "round"],
        f"the auction has ended ({ended['status']}): its last round was 1",
    )


def held_round(
    client: TestClient, prefix: str, first_seed: int, seed: int
) -> tuple[int, int, str, bytes, Any]:
    """A remote auction whose round 1 (2 s) is open and that no step will close for a few
    seconds (``hold_claims``): its id, an asked patron's model id and token, that patron's
    faithful upload, and the app's database."""
    auction_id, manifests, patrons = start_remote(
        client, prefix, first_seed, 3, round_deadline_s=2.0, seed=seed
    )
    state = open_round(client, auction_id)
    database = client.app.state.services.database  # type: ignore[attr-defined]
    database.hold_claims()
    position = next(i for i, (m, _) in enumerate(patrons) if m in state["asked"])
    model_id, token = patrons[position]
    info = RoundInfo.from_state(state, position)
    body = faithful_fine_tune(parse_manifest(manifests[position]), info).model_dump_json()
    return auction_id, model_id, token, body.encode(), database


def test_a_patron_judged_late_is_in_time_once_an_outage_pushed_the_deadline_back(
    client: TestClient,
) -> None:
    """A patron whose upload came after the deadline (410, recorded late) sends it again
    after a database outage gave the round its time back (``crud.push_back_deadlines``, as
    the lease runner does once the database answers again, on this replica or another): it
    is in time and accepted (the late answer is made this one; it was a 500)."""
    auction_id, model_id, token, body, database = held_round(client, "late-then", 430, 6)
    time.sleep(client.get(f"/auctions/{auction_id}/rounds/current").json()["seconds_left"])
    late = put(client, auction_id, 1, model_id, body, token)
    assert late.status_code == 410, late.text
    with database.session(write=True) as session:
        now = datetime.now(UTC)
        moved, _ = crud.push_back_deadlines(
            session, began=now - timedelta(seconds=1), now=now, retry=timedelta(seconds=2)
        )
        session.commit()
    assert auction_id in moved
    again = put(client, auction_id, 1, model_id, body, token)
    assert again.status_code == 200 and again.json()["outcome"] == "accepted", again.text
    [round_1] = client.get(f"/auctions/{auction_id}").json()["fine_tuning"]
    outcomes = {a["model_id"]: a["outcome"] for a in round_1["answers"]}
    assert outcomes[model_id] == "accepted", round_1


def test_until_an_outage_is_given_back_a_late_upload_is_told_to_come_again(
    client: TestClient, settings: Settings
) -> None:
    """After this process met a database outage and before its lease runner has given the
    open rounds their time back, an upload that would be late is answered as in the outage
    (503 with Retry-After), not 410: the push may still make it in time. Once the time is
    given back (here it cannot be for this round, whose deadline passed before the outage),
    the same upload is late as ever. The push is held back by a lock on another open round
    (PostgreSQL's row locks; the push locks the open rounds in id order)."""
    if is_sqlite(settings.database_url):
        pytest.skip("PostgreSQL's row locks hold the push back")
    held, _, _ = start_remote(client, "held-open", 440, 3, round_deadline_s=120.0, seed=7)
    open_round(client, held)
    auction_id, model_id, token, body, database = held_round(client, "told-again", 450, 8)
    # Past the deadline by more than the lease runner's longest wait between two passes, so
    # the outage (begun at the app's last statement) begins after the deadline; still in the
    # grace (5 s), so no step closes the round.
    left = client.get(f"/auctions/{auction_id}/rounds/current").json()["seconds_left"]
    database.hold_claims()  # the grace counts from now
    time.sleep(left + 2.5)
    engine = create_engine(settings.database_url)
    try:
        with engine.connect() as locker:
            locker.execute(
                text("SELECT id FROM fine_tune_rounds WHERE auction_id = :a FOR UPDATE"),
                {"a": held},
            )
            database.note_outage()  # as an outage would: the push now waits for the lock
            told = put(client, auction_id, 1, model_id, body, token)
            assert told.status_code == 503, told.text
            assert int(told.headers["retry-after"]) > 0
            assert loc_of(told) == [["database"]] and "send the same body again" in told.text
            locker.rollback()
        wait_for(lambda: {"began": database.outage_began()}, lambda s: s["began"] is None, 10)
    finally:
        engine.dispose()
    late = put(client, auction_id, 1, model_id, body, token)
    assert late.status_code == 410, late.text


def test_an_upload_refused_by_a_write_lock_held_past_the_busy_timeout_counts_on_its_retry(
    client: TestClient, settings: Settings, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Another process holding SQLite's write lock longer than the API waits for it (its busy
    timeout, 2 s here; an operator's transaction, a VACUUM) is an outage of writes: an upload
    that arrived in time is answered 503 with its arrival kept, the round gets back the time
    it had left, and the same body sent again once the lock is free counts in time (it was
    410, late: the step closed the round at its deadline as soon as the lock was free)."""
    if not is_sqlite(settings.database_url):
        pytest.skip("SQLite's write lock")
    monkeypatch.setattr(db_module, "SQLITE_BUSY_TIMEOUT_MS", 2_000)  # the API's, not the steps'
    auction_id, manifests, patrons = start_remote(
        client, "stalled", 460, 3, round_deadline_s=3.0, seed=9
    )
    state = open_round(client, auction_id)
    position = next(i for i, (m, _) in enumerate(patrons) if m in state["asked"])
    model_id, token = patrons[position]
    info = RoundInfo.from_state(state, position)
    body = faithful_fine_tune(parse_manifest(manifests[position]), info).model_dump_json()
    holder = sqlite3.connect(sqlite_path(settings.database_url), isolation_level=None)
    holder.execute("BEGIN IMMEDIATE")
    try:
        refused = put(client, auction_id, 1, model_id, body.encode(), token)
        time.sleep(max(0.0, state["seconds_left"] - 2.0) + 2.5)  # past the deadline
    finally:
        holder.execute("ROLLBACK")
        holder.close()
    assert refused.status_code == 503, refused.text
    assert loc_of(refused) == [["database"]] and "retry-after" in refused.headers
    time.sleep(1.5)  # the step due at the deadline runs once the lock is free
    again = put(client, auction_id, 1, model_id, body.encode(), token)
    assert again.status_code == 200, again.text
    assert again.json()["outcome"] in ("accepted", "held")
    closed = wait_for(
        lambda: client.get(f"/auctions/{auction_id}").json()["fine_tuning"][0],
        lambda r: r["status"] == "closed",
        ROUND_WAIT_S,
    )
    outcomes = {a["model_id"]: a["outcome"] for a in closed["answers"]}
    assert outcomes[model_id] == again.json()["outcome"], closed


def _seconds(stamp: str) -> float:
    return datetime.fromisoformat(stamp.replace("Z", "+00:00")).timestamp()


def test_an_upload_waiting_for_the_write_lock_stalls_no_other_request(
    client: TestClient, settings: Settings
) -> None:
    """An upload's writes run at once on the event loop when SQLite's write lock is free; when
    another writer holds it, the upload waits in a thread and every other request is served
    meanwhile. Once the lock is free the upload is stored and answered."""
    if not is_sqlite(settings.database_url):
        pytest.skip("SQLite's write lock")
    auction_id, model_id, token, upload = first_asked_upload(
        remote_auction(client, "locked", 420, seed=3)
    )
    answers: list[Any] = []
    waiting = threading.Thread(
        target=lambda: answers.append(
            put(client, auction_id, 1, model_id, upload.model_dump_json().encode(), token)
        )
    )
    # Another writer holds the lock (as an auction worker does while it commits).
    holder = sqlite3.connect(sqlite_path(settings.database_url), isolation_level=None)
    holder.execute("BEGIN IMMEDIATE")
    try:
        waiting.start()
        time.sleep(1.0)  # the upload reaches the server and waits for the lock
        reads: list[Any] = []
        reader = threading.Thread(
            target=lambda: reads.append(client.get(f"/auctions/{auction_id}")), daemon=True
        )
        reader.start()
        reader.join(timeout=30)
        assert reads and reads[0].status_code == 200, "a read stalled behind the upload"
        assert waiting.is_alive() and not answers, (
            "the upload did not wait for the lock",
            answers and (answers[0].status_code, answers[0].text),
        )
    finally:
        holder.execute("ROLLBACK")
        holder.close()
    waiting.join(timeout=60)
    assert answers and answers[0].status_code == 200, answers and answers[0].text
    assert answers[0].json()["round"] == 1 and answers[0].json()["outcome"] in ("accepted", "held")
    auction = client.get(f"/auctions/{auction_id}").json()
    outcomes = {a["model_id"]: a["outcome"] for a in auction["fine_tuning"][0]["answers"]}
    assert outcomes[model_id] == answers[0].json()["outcome"]


def test_the_same_upload_sent_at_once_gets_one_answer(client: TestClient) -> None:
    """Two identical uploads of one patron racing each other (an agent's retry over a second
    connection; two is a token's share of uploads in flight) are stored once, and both get the
    same answer: never a 500 of the second insert."""
    auction_id, model_id, token, upload = first_asked_upload(
        remote_auction(client, "racing", 640, seed=9)
    )
    raw = upload.model_dump_json().encode()
    start = threading.Barrier(2)
    answers: list[Any] = []

    def send() -> None:
        start.wait()
        answers.append(put(client, auction_id, 1, model_id, raw, token))

    racers = [threading.Thread(target=send) for _ in range(2)]
    for racer in racers:
        racer.start()
    for racer in racers:
        racer.join(timeout=120)
    assert [a.status_code for a in answers] == [200] * 2, [a.text for a in answers]
    assert len({a.content for a in answers}) == 1
    auction = client.get(f"/auctions/{auction_id}").json()
    mine = [a for a in auction["fine_tuning"][0]["answers"] if a["model_id"] == model_id]
    assert len(mine) == 1 and mine[0]["outcome"] == answers[0].json()["outcome"]


def test_a_failed_auction_closes_its_open_round(client: TestClient, settings: Settings) -> None:
    """An auction that fails while a round is open (here its checkpoint cannot be restored
    when the round's deadline comes) closes that round with it, as a cancel does: nobody is
    told to answer a round of an auction that is over."""
    auction_id, _, _ = start_remote(client, "failing", 700, 4, round_deadline_s=2, seed=4)
    state = open_round(client, auction_id)
    assert state["status"] == "open", state
    engine = create_engine(settings.database_url)
    try:
        with engine.begin() as connection:
            connection.execute(
                text("UPDATE auctions SET checkpoint = :junk WHERE id = :id"),
                {"junk": b"not a checkpoint", "id": auction_id},
            )
    finally:
        engine.dispose()
    failed = wait_for(
        lambda: client.get(f"/auctions/{auction_id}").json(),
        lambda a: a["status"] not in ("pending", "running"),
        ROUND_WAIT_S,
    )
    assert failed["status"] == "failed" and "cannot resume" in failed["error"]
    (closed,) = failed["fine_tuning"]
    assert closed["status"] == "closed" and closed["closed_at"] is not None
    now = client.get(f"/auctions/{auction_id}/rounds/current").json()
    assert now["auction_status"] == "failed" and now["status"] == "closed"
