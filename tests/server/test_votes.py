"""Every vote explained (GET /auctions/{id}/iterations/{n}/votes/{model_id}) and the lists'
filters and order (GET /auctions, /jobs: ?status=&kind=&order=); in-process, on SQLite and
PostgreSQL."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient

from agents.forward import ACTIONS
from agents.manifest import DECISIONS, ES_NEURONS, INPUTS, parse_manifest
from server.app import create_app
from tests.support.factories import honest, unique
from tests.support.server import ADMIN, make_settings, wait_for

SHORT_FISH = {"kind": "fish", "params": {"steps": 30, "srd": True, "seed": 4}}
LONG_STUDY = {"kind": "auction-study", "params": {"trials": 50}}  # always cancelled


def finished_auction(client: TestClient, name: str, **settings: Any) -> dict[str, Any]:
    """A finished auction of five honest patrons over two fish, with ``settings``."""
    bodies = [honest(unique(name), seed=s) for s in (0, 2, 3, 4, 5)]  # seed 1 is held for review
    ids = [client.post("/submit", json=body).json()["model_id"] for body in bodies]
    body = {"n_fish": 2, "model_ids": ids, "seed": 3, **settings}
    auction_id = client.post("/auctions", json=body, headers=ADMIN).json()["auction_id"]
    return dict(
        wait_for(
            lambda: client.get(f"/auctions/{auction_id}").json(),
            lambda a: a["status"] == "finished",
            timeout_s=120,
        )
    )


@pytest.fixture(scope="module")
def auction(client: TestClient) -> dict[str, Any]:
    return finished_auction(client, "voter")


def test_a_vote_explains_the_self_judges_judgements_behind_its_verdicts(
    client: TestClient,
) -> None:
    """The PFC's judgements PGL, BC, FQ are explained with each vote: read from the softmax of
    the sensor and the decision by the judgement's weights, and read by the verdicts through
    their tanh. With one copy (no noise averaged in) both hold exactly, from the manifest."""
    bodies = [honest(unique("judged"), seed=s) for s in (0, 2, 3)]
    for body in bodies:
        body["augmentation"]["copies"] = 1
    ids = [client.post("/submit", json=body).json()["model_id"] for body in bodies]
    body = {"n_fish": 1, "model_ids": ids, "seed": 3}
    auction_id = client.post("/auctions", json=body, headers=ADMIN).json()["auction_id"]
    auction = wait_for(
        lambda: client.get(f"/auctions/{auction_id}").json(),
        lambda a: a["status"] == "finished",
        timeout_s=120,
    )
    pfc = {m: bodies[ids.index(m)]["pfc"] for m in ids}
    checked = 0
    for row in auction["history"]:
        path = f"/auctions/{auction_id}/iterations/{row['iteration']}/votes"
        for vote in client.get(path).json()["votes"]:
            judgement, mine = vote["judgement"], pfc[vote["model_id"]]
            assert list(judgement) == ["PGL", "BC", "FQ"]
            read = {**vote["sensor"], **vote["decision"]}
            top = max(read.values())
            soft = {k: math.exp(v - top) for k, v in read.items()}
            soft = {k: v / sum(soft.values()) for k, v in soft.items()}
            for name, neuron in mine["judgement"].items():
                weighed = sum(w * soft[k] for k, w in neuron["weights"].items())
                assert judgement[name] == pytest.approx(weighed + neuron["bias"], abs=1e-9)
            for name, neuron in mine["verdict"].items():
                weighed = sum(w * math.tanh(judgement[k]) for k, w in neuron["weights"].items())
                assert vote["pfc"][name] == pytest.approx(weighed + neuron["bias"], abs=1e-9)
            checked += 1
    assert checked >= 3


@pytest.fixture(scope="module")
def tuned(client: TestClient) -> dict[str, Any]:
    """Its market fine-tunes the patrons after its first 3 rounds."""
    return finished_auction(client, "tuned", fine_tune=True, fine_tune_rounds=3)


@pytest.mark.postgres_in_slow_run
def test_every_vote_of_every_iteration_is_explained(
    client: TestClient, auction: dict[str, Any]
) -> None:
    bought_at = {b["model_id"]: b["iteration"] for b in auction["buyers"]}
    left: set[int] = set()
    for row in auction["history"]:
        n = row["iteration"]
        counts = dict.fromkeys(ACTIONS, 0)
        for model_id in auction["model_ids"]:
            response = client.get(f"/auctions/{auction['id']}/iterations/{n}/votes/{model_id}")
            if model_id in left:
                assert response.status_code == 404, response.text
                detail = response.json()["detail"][0]
                assert detail["loc"] == ["path", "model_id"]
                assert detail["msg"].endswith(
                    f"did not vote in iteration {n} of auction {auction['id']}: it had left the "
                    "auction (patrons leave when they buy or quit)"
                ), detail
                continue
            assert response.status_code == 200, response.text
            vote = response.json()
            assert (vote["auction_id"], vote["iteration"], vote["model_id"]) == (
                auction["id"],
                n,
                model_id,
            )
            model = client.get(f"/models/{model_id}").json()
            assert (vote["participant"], vote["version"]) == (
                model["participant"],
                model["version"],
            )
            assert list(vote["sensor"]) == list(ES_NEURONS)
            assert list(vote["decision"]) == list(DECISIONS) and list(vote["pfc"]) == ["T", "F"]
            logits = [vote["decision"][name] for name in DECISIONS]
            assert vote["vote"] == ACTIONS[logits.index(max(logits))]  # the largest logit won
            assert list(vote["row"]) == list(INPUTS)
            # the row the network read, exactly; the iteration's price is recorded to 5 decimals
            assert round(vote["row"]["price"], 5) == row["price"]
            counts[vote["vote"]] += 1
            if bought_at.get(model_id) == n:
                assert vote["vote"] == "buy"
            if vote["vote"] == "quit" or bought_at.get(model_id) == n:
                left.add(model_id)
        assert counts == row["votes"]  # the explanations are exactly the iteration's votes


def test_an_iterations_votes_are_listed_in_one_read(
    client: TestClient, auction: dict[str, Any]
) -> None:
    for row in auction["history"]:
        n = row["iteration"]
        response = client.get(f"/auctions/{auction['id']}/iterations/{n}/votes")
        assert response.status_code == 200, response.text
        listed = response.json()
        assert (listed["auction_id"], listed["iteration"]) == (auction["id"], n)
        assert round(listed["row"]["price"], 5) == row["price"]
        counts = dict.fromkeys(ACTIONS, 0)
        for vote in listed["votes"]:
            counts[vote["vote"]] += 1
            one = client.get(
                f"/auctions/{auction['id']}/iterations/{n}/votes/{vote['model_id']}"
            ).json()
            where = {"auction_id": auction["id"], "iteration": n, "row": listed["row"]}
            assert one == {**vote, **where}
            # no remote rounds: every patron bids with the version it entered with
            assert vote["version_id"] == vote["model_id"]
        assert counts == row["votes"]
        voters = [vote["model_id"] for vote in listed["votes"]]
        assert voters == [m for m in auction["model_ids"] if m in voters]  # in patron order
    missing = client.get(f"/auctions/{auction['id']}/iterations/999/votes")
    assert missing.status_code == 404
    assert missing.json()["detail"][0]["loc"] == ["path", "iteration"]


@pytest.mark.postgres_in_slow_run
def test_every_vote_names_the_weights_that_cast_it(
    client: TestClient, auction: dict[str, Any], tuned: dict[str, Any]
) -> None:
    numbers = ("external_sensor", "decision", "pfc")
    afters: list[int] = []
    for one in (auction, tuned):
        entered = {m: client.get(f"/models/{m}").json()["manifest"] for m in one["model_ids"]}
        last: dict[int, tuple[int | None, dict[str, Any]]] = {}  # the iteration before's
        for row in one["history"]:
            n = row["iteration"]
            votes = client.get(f"/auctions/{one['id']}/iterations/{n}/votes").json()["votes"]
            for vote in votes:
                path = f"/auctions/{one['id']}/iterations/{n}/votes/{vote['model_id']}"
                response = client.get(path + "/weights")
                assert response.status_code == 200, response.text
                weights = response.json()
                assert client.get(path).json()["fine_tuned_after"] == vote["fine_tuned_after"]
                assert {k: weights[k] for k in ("participant", "version", "version_id")} == {
                    k: vote[k] for k in ("participant", "version", "version_id")
                }
                assert (weights["iteration"], weights["fine_tuned_after"]) == (
                    n,
                    vote["fine_tuned_after"],
                )
                manifest = parse_manifest(weights["manifest"])  # a manifest as /submit takes it
                mine = entered[vote["model_id"]]
                after = vote["fine_tuned_after"]
                assert vote["weights_kept"] is True
                if after is None:  # the version's own weights
                    assert weights["manifest"] == mine
                else:  # fine-tuned inside the market after one of its first 3 rounds
                    assert one is tuned and 0 <= after < min(n, 3), (n, vote)
                    assert manifest.participant == mine["participant"]
                    assert weights["manifest"]["fine_tuning"] == mine["fine_tuning"]
                    assert [k for k in numbers if weights["manifest"][k] != mine[k]], "no move"
                    afters.append(after)
                # every fine-tuning in the market before this vote, kept or refused
                tunings = weights["fine_tunings"]
                tunes = one is tuned and mine["fine_tuning"]["epochs"] > 0
                made = list(range(min(n, 3))) if tunes else []
                assert [f["after"] for f in tunings] == made
                assert max((f["after"] for f in tunings if f["kept"]), default=None) == after
                assert all(f["reasons"] == [] for f in tunings if f["kept"])
                before = last.get(vote["model_id"])
                if before is not None and before[0] == after:  # no fine-tuning kept since
                    assert weights["manifest"] == before[1]
                elif before is not None:
                    assert weights["manifest"] != before[1]
                last[vote["model_id"]] = (after, weights["manifest"])
    assert afters, "the market fine-tuned nobody"


def test_a_fine_tuning_the_re_screening_refuses_is_recorded_and_the_weights_before_vote_on(
    tmp_path: Path,
) -> None:
    """A server whose review margin is 1 holds every fine-tuned version for an inspector, so
    its market refuses every fine-tuning: each is recorded as refused, and the versions' own
    weights vote throughout."""
    settings = make_settings(f"sqlite:///{tmp_path / 'srd.db'}", tmp_path / "data")
    with TestClient(create_app(settings)) as client:  # admitted at the default margin of tests
        bodies = [honest(unique("refused"), seed=s) for s in (2, 3, 4)]
        ids = [client.post("/submit", json=body).json()["model_id"] for body in bodies]
    strict = settings.model_copy(update={"review_margin": 1.0})
    with TestClient(create_app(strict)) as client:
        body = {"n_fish": 1, "model_ids": ids, "seed": 3, "fine_tune": True, "fine_tune_rounds": 3}
        auction_id = client.post("/auctions", json=body, headers=ADMIN).json()["auction_id"]
        auction = wait_for(
            lambda: client.get(f"/auctions/{auction_id}").json(),
            lambda a: a["status"] == "finished",
            timeout_s=120,
        )
        assert len(auction["history"]) > 1
        for row in auction["history"][1:]:
            n = row["iteration"]
            votes = client.get(f"/auctions/{auction_id}/iterations/{n}/votes").json()["votes"]
            assert votes
            for vote in votes:
                path = f"/auctions/{auction_id}/iterations/{n}/votes/{vote['model_id']}/weights"
                weights = client.get(path).json()
                assert weights["fine_tuned_after"] is vote["fine_tuned_after"] is None
                tunings = weights["fine_tunings"]
                assert [(f["after"], f["kept"]) for f in tunings] == [
                    (k, False) for k in range(min(n, 3))
                ]
                for f in tunings:  # each says which bar held it, in the screener's words
                    assert f["reasons"], f
                    assert {"rule", "neuron", "message"} == set(f["reasons"][0])
                    assert "review-margin" in {r["rule"] for r in f["reasons"]}, f
                own = client.get(f"/models/{vote['model_id']}").json()["manifest"]
                assert weights["manifest"] == own


@pytest.mark.parametrize(
    ("path", "status", "loc", "words"),
    [
        ("/auctions/999999/iterations/0/votes/1", 404, ["path", "auction_id"], "does not exist"),
        ("/auctions/{id}/iterations/999/votes/{voter}", 404, ["path", "iteration"], "no committed"),
        ("/auctions/{id}/iterations/0/votes/999999", 404, ["path", "model_id"], "did not vote"),
        (
            "/auctions/{id}/iterations/-1/votes/{voter}",
            422,
            ["path", "iteration"],
            "without a sign",
        ),
        ("/auctions/{id}/iterations/1.0/votes/{voter}", 422, ["path", "iteration"], "digits"),
        ("/auctions/{id}/iterations/0/votes/0", 422, ["path", "model_id"], ""),
        ("/auctions/{id}/iterations/999/votes/{voter}/weights", 404, ["path", "iteration"], ""),
        ("/auctions/{id}/iterations/0/votes/999999/weights", 404, ["path", "model_id"], "did not"),
    ],
)
def test_explanation_errors_name_the_part_of_the_path(
    client: TestClient, auction: dict[str, Any], path: str, status: int, loc: list[str], words: str
) -> None:
    url = path.format(id=auction["id"], voter=auction["model_ids"][0])
    response = client.get(url)
    assert response.status_code == status, response.text
    detail = response.json()["detail"][0]
    assert detail["loc"] == loc and words in detail["msg"]


def test_the_explanation_endpoint_is_documented(client: TestClient) -> None:
    paths = client.get("/openapi.json").json()["paths"]
    operation = paths["/auctions/{auction_id}/iterations/{iteration}/votes/{model_id}"]["get"]
    assert operation["operationId"] == "explain_vote"
    assert {"200", "404", "422"} <= set(operation["responses"])


def ids_of(client: TestClient, path: str, **params: Any) -> list[int]:
    """Every id of a list with ``params``, one item per page (so the cursor is followed)."""
    ids: list[int] = []
    query: dict[str, Any] = {"limit": 1, **params}
    while True:
        body = client.get(path, params=query).json()
        ids += [item["id"] for item in body["items"]]
        if body["next_cursor"] is None:
            return ids
        query["cursor"] = body["next_cursor"]


def test_auction_list_filters_by_status_and_sorts_both_ways(
    client: TestClient, auction: dict[str, Any]
) -> None:
    newest = ids_of(client, "/auctions")
    oldest = ids_of(client, "/auctions", order="oldest")
    assert oldest == sorted(newest) and newest == sorted(newest, reverse=True) and newest
    finished = ids_of(client, "/auctions", status="finished")
    assert auction["id"] in finished
    assert all(client.get(f"/auctions/{i}").json()["status"] == "finished" for i in finished)
    assert auction["id"] not in ids_of(client, "/auctions", status="running")


@pytest.mark.postgres_in_slow_run  # its filters are SQL the storage tests run on PostgreSQL
def test_job_list_filters_by_status_and_kind(client: TestClient) -> None:
    fish = client.post("/jobs", json=SHORT_FISH, headers=ADMIN).json()["job_id"]
    study = client.post("/jobs", json=LONG_STUDY, headers=ADMIN).json()["job_id"]
    assert client.delete(f"/jobs/{study}", headers=ADMIN).status_code == 200
    wait_for(
        lambda: client.get(f"/jobs/{fish}").json(),
        lambda j: j["status"] == "succeeded",
        timeout_s=120,
    )
    assert fish in ids_of(client, "/jobs", kind="fish")
    assert study not in ids_of(client, "/jobs", kind="fish")
    assert ids_of(client, "/jobs", kind="auction-study", status="cancelled")[:1] == [study]
    assert fish in ids_of(client, "/jobs", status="succeeded", kind="fish", order="oldest")
    assert ids_of(client, "/jobs", order="oldest") == sorted(ids_of(client, "/jobs"))
    for item in client.get("/jobs", params={"status": "cancelled"}).json()["items"]:
        assert item["status"] == "cancelled"


@pytest.mark.parametrize(
    ("path", "params", "field"),
    [
        ("/jobs", {"status": "done"}, "status"),
        ("/jobs", {"kind": "poker"}, "kind"),
        ("/jobs", {"order": "random"}, "order"),
        ("/auctions", {"status": "sold"}, "status"),
        ("/auctions", {"order": "up"}, "order"),
    ],
)
def test_bad_list_parameters_are_422_naming_them(
    client: TestClient, path: str, params: dict[str, str], field: str
) -> None:
    response = client.get(path, params=params)
    assert response.status_code == 422
    assert response.json()["detail"][0]["loc"] == ["query", field]
