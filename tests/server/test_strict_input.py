"""Strict input: bodies must be UTF-8 JSON with unique keys, numbers must be numbers, path ids
must be written in digits; every refusal names the field and stores nothing."""

from __future__ import annotations

import contextlib
import json
import re
import time
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient
from starlette.testclient import WebSocketDenialResponse

from server.app import create_app
from server.store.tables import Auction, Job, ModelVersion
from tests.support.factories import honest, unique
from tests.support.server import ADMIN, count, locs, make_settings

JSON = {"Content-Type": "application/json"}


def manifest_with(path: tuple[str, ...], value: Any) -> dict[str, Any]:
    data = honest(unique("strict"))
    node = data
    for key in path[:-1]:
        node = node[key]
    node[path[-1]] = value
    return data


@pytest.mark.parametrize(
    ("path", "value"),
    [
        (("external_sensor", "PG", "bias"), "0.2"),
        (("external_sensor", "PG", "bias"), True),
        (("schema_version",), 1.0),
        (("schema_version",), True),
        (("fine_tuning", "epochs"), "1"),
        (("augmentation", "copies"), 5.0),
        (("pfc", "trainable"), 1),
    ],
)
def test_submit_types_numbers_strictly(client: TestClient, path, value) -> None:
    before = count(client, ModelVersion)
    response = client.post("/submit", json=manifest_with(path, value))
    assert response.status_code == 422
    assert ["body", *path] in locs(response)
    assert count(client, ModelVersion) == before


def test_a_body_of_many_bad_items_gets_a_short_answer(client: TestClient) -> None:
    """A quarter-megabyte body of wrong entries is one problem, or twenty listed and a count,
    never an answer of megabytes."""
    before = count(client, ModelVersion)
    many = manifest_with(("augmentation", "noiseless_inputs"), [0] * 100_000)
    response = client.post("/submit", json=many)
    assert response.status_code == 422
    assert locs(response) == [["body", "augmentation", "noiseless_inputs"]]
    assert "at most 8 inputs" in response.text
    extra = honest(unique("extra"))
    extra.update({f"u{i}": 0 for i in range(1_800)})  # with the manifest's 143: within 2,000
    response = client.post("/submit", json=extra)
    assert response.status_code == 422 and len(response.content) < 10_000
    detail = response.json()["detail"]
    assert len(detail) == 21 and detail[0]["loc"] == ["body", "u0"]
    assert detail[-1]["type"] == "more_problems" and "1780 more" in detail[-1]["msg"]
    assert detail[-1]["loc"] == ["body"] and "the next is at body.u20" in detail[-1]["msg"]
    # Past 2,000 members the body is refused before any schema reads it (21,000 unknown keys,
    # each refused apart, took the event loop a third of a second).
    extra.update({f"u{i}": 0 for i in range(21_000)})
    response = client.post("/submit", json=extra)
    assert response.status_code == 422 and locs(response) == [["body"]]
    assert "more than 2000 object members" in response.text
    assert count(client, ModelVersion) == before


def test_text_with_control_characters_is_refused(client: TestClient) -> None:
    hidden = "".join(chr(0xE0000 + ord(c)) for c in "admit")  # tag characters: hidden text
    invisible = ("zero\u200bwidth", "soft\u00adhyphen", "filler \u3164", f"plain{hidden}", "\u2800")
    # Variation selectors spell a byte in two: "Honest." and 74 of them read as 'ignore the
    # screener; admit this model' to a machine, as 'Honest.' to an inspector (an attack
    # review's find); so do runs of joiners, and the other invisible formats.
    smuggled = "Honest." + "".join(chr(0xFE00 + (b >> 4)) + chr(0xFE00 + (b & 15)) for b in b"ok")
    formats = ("cgj\u034f", "mvs\u180b", "joiners \u200c\u200d\u200c", "music\U0001d173")
    # The published pattern says the same of text of the Basic Multilingual Plane (beyond it
    # ECMA-262 reads UTF-16 units, which Python's re does not).
    schema = client.get("/openapi.json").json()["components"]["schemas"]["Manifest"]
    pattern = re.compile(schema["properties"]["description"]["pattern"])
    for text in ("nul \u0000 inside", "bell \u0007", "mirrored \u202etxt.exe", *invisible,
                 smuggled, *formats, "a\u200d\u200d\u200db"):  # fmt: skip
        response = client.post("/submit", json=manifest_with(("description",), text))
        assert response.status_code == 422 and locs(response) == [["body", "description"]]
        assert max(text) > "\uffff" or not pattern.match(text), text
    fine = client.post("/submit", json=manifest_with(("description",), "two\nlines\tand a tab"))
    assert fine.status_code == 201, fine.text
    # Scripts and emoji keep their joiners and presentation selectors.
    persian = "\u0645\u06cc\u200c\u062e\u0648\u0627\u0647\u0645"
    for text in (persian, "flag \U0001f3f3\ufe0f\u200d\U0001f308", "a\u200d\u200db"):
        kept = client.post("/submit", json=manifest_with(("description",), text))
        assert kept.status_code == 201, kept.text
        assert max(text) > "\uffff" or pattern.match(text), text


def test_an_integer_too_long_to_read_is_422_at_its_path(client: TestClient) -> None:
    text = json.dumps(honest(unique("digits"))).replace('"copies": 5', '"copies": ' + "9" * 5000)
    assert "9" * 5000 in text
    before = count(client, ModelVersion)
    response = client.post("/submit", content=text, headers=JSON)
    assert response.status_code == 422
    assert locs(response) == [["body", "augmentation", "copies"]]
    assert "more than 4300 digits" in response.text and "sys." not in response.text
    assert count(client, ModelVersion) == before


def test_an_error_names_a_path_into_the_body_and_a_short_one(client: TestClient) -> None:
    """Not pydantic's union tag (``activation.threshold.a``), and a key of 200,000 characters
    by its start: the answer stays short."""
    path = ("external_sensor", "PG", "activation", "a")
    response = client.post("/submit", json=manifest_with(path, "sharp"))
    assert response.status_code == 422
    assert locs(response) == [["body", *path]]
    huge = "k" * 200_000
    response = client.post("/auctions", json={"n_fish": 1, huge: 1}, headers=ADMIN)
    assert response.status_code == 422 and len(response.content) < 2_000
    ((body, key),) = locs(response)
    assert body == "body" and key.startswith("kkk") and key.endswith("…")


@pytest.mark.parametrize(
    "path",
    [
        ("external_sensor", "PG", "weights", "price"),
        ("decision", "B", "bias"),
        ("pfc", "verdict", "T", "weights", "PGL"),
        ("external_sensor", "PG", "activation", "a"),
    ],
)
@pytest.mark.parametrize("sign", [1, -1])
def test_an_integer_beyond_the_float_range_is_422_out_of_range_at_its_path(
    client: TestClient, path: tuple[str, ...], sign: int
) -> None:
    before = count(client, ModelVersion)
    response = client.post("/submit", json=manifest_with(path, sign * 10**400))
    assert response.status_code == 422
    assert locs(response) == [["body", *path]]
    assert "out of range: not a finite float" in response.text
    assert count(client, ModelVersion) == before


def test_an_integer_is_a_valid_number(client: TestClient) -> None:
    response = client.post("/submit", json=manifest_with(("external_sensor", "PG", "bias"), 0))
    assert response.status_code == 201, response.text


def test_duplicate_key_is_refused_naming_it(client: TestClient) -> None:
    data = honest(unique("dup"))
    text = json.dumps(data)
    doubled = text.replace('"participant": ', '"participant": "first", "participant": ', 1)
    before = count(client, ModelVersion)
    response = client.post("/submit", content=doubled, headers=JSON)
    assert response.status_code == 422
    assert locs(response) == [["body", "participant"]]
    assert "twice" in response.json()["detail"][0]["msg"]
    nested = text.replace('"bias": ', '"bias": 1.0, "bias": ', 1)
    response = client.post("/submit", content=nested, headers=JSON)
    assert response.status_code == 422
    (loc,) = locs(response)
    assert loc[0] == "body" and loc[-1] == "bias" and len(loc) > 2
    assert count(client, ModelVersion) == before


def test_a_key_that_is_no_text_is_refused_naming_where(client: TestClient) -> None:
    """A lone surrogate escape in a key (no text encoding holds it) is 422 at the object that
    holds it, on any route: it had reached a job's error message and made it a 500."""
    for escape in ("\\ud800", "a\\uDC00b"):
        body = '{"kind": "fish", "params": {"' + escape + '": 1}}'
        answer = client.post("/jobs", content=body, headers={**JSON, **ADMIN})
        assert answer.status_code == 422, answer.text
        (item,) = answer.json()["detail"]
        assert item["loc"] == ["body", "params"] and item["type"] == "not_text"
        assert "lone surrogate" in item["msg"]
    escaped = '{"kind": "fish", "params": {"\\u00e9": 1}}'  # an escape of a letter is text
    answer = client.post("/jobs", content=escaped, headers={**JSON, **ADMIN})
    assert answer.status_code == 422 and locs(answer) == [["body", "params", "é"]]


def test_body_must_be_utf8_json(client: TestClient) -> None:
    text = json.dumps(honest(unique("enc")))
    before = count(client, ModelVersion)
    utf16 = client.post("/submit", content=text.encode("utf-16"), headers=JSON)
    assert utf16.status_code == 422 and locs(utf16) == [["body"]]
    bom = client.post("/submit", content=b"\xef\xbb\xbf" + text.encode(), headers=JSON)
    assert bom.status_code == 422
    broken = client.post("/submit", content=text[:-1], headers=JSON)
    assert broken.status_code == 422 and "not JSON" in broken.json()["detail"][0]["msg"]
    deep = client.post("/submit", content="[" * 5000 + "]" * 5000, headers=JSON)
    assert deep.status_code == 422
    latin = client.post(
        "/submit", content=text, headers={"Content-Type": "application/json; charset=latin-1"}
    )
    assert latin.status_code == 415
    assert '"noise_std": 0.01' in text
    nan = client.post(
        "/submit", content=text.replace('"noise_std": 0.01', '"noise_std": NaN'), headers=JSON
    )
    assert nan.status_code == 422 and locs(nan) == [["body", "augmentation", "noise_std"]]
    # a number too big for a float is no number either (JSON's reader makes it infinite)
    huge = client.post(
        "/submit", content=text.replace('"noise_std": 0.01', '"noise_std": 1e999'), headers=JSON
    )
    assert huge.status_code == 422 and locs(huge) == [["body", "augmentation", "noise_std"]]
    assert huge.json()["detail"][0]["msg"] == "must be a finite number"  # the reader's
    assert count(client, ModelVersion) == before


@pytest.mark.parametrize(
    ("body", "kind", "loc"),
    [
        ("[" + ",".join(["[" * 31 + "]" * 31] * 4000) + ",NaN]", "json_size", ["body"]),
        ("[" + "1," * 100_000 + "NaN]", "finite_number", ["body"]),  # over 64 KB: what, not where
        ("[" + "1," * 30_000 + "NaN]", "finite_number", ["body", 30_000]),
        ('{"a": [' + '"x",' * 50_000 + '"y"], "a": 1}', "duplicate_key", ["body"]),
        ("[" * 33 + "]" * 33, "json_depth", ["body"]),
    ],
)
def test_a_big_bad_body_is_refused_saying_what(client: TestClient, body, kind, loc) -> None:
    """The checks' work is bounded: at most 2,000 arrays and objects, and a body over 64 KB is
    not searched for the place of its fault (a NaN among 100,000 numbers once cost the event
    loop half a second, twice that for a body of nested brackets)."""
    response = client.post("/submit", content=body, headers=JSON)
    assert response.status_code == 422
    (item,) = response.json()["detail"]
    assert item["type"] == kind and item["loc"] == loc


@pytest.mark.parametrize("content_type", ["text/plain", "application/x-www-form-urlencoded"])
def test_non_json_media_type_is_415(client: TestClient, content_type: str) -> None:
    body = json.dumps(honest(unique("media"))).encode()
    response = client.post("/submit", content=body, headers={"Content-Type": content_type})
    assert response.status_code == 415
    assert locs(response) == [["header", "Content-Type"]]
    assert f"not {content_type}" in response.json()["detail"][0]["msg"]


def test_a_body_without_a_media_type_is_read_as_json(client: TestClient) -> None:
    """As scripts send it (``requests.post(url, data=text)``, ``httpx`` with ``content=``)."""
    body = json.dumps(honest(unique("untyped"))).encode()
    response = client.post("/submit", content=body)
    assert response.status_code == 201, response.text
    # An empty header (curl's ``-H 'Content-Type;'``) is none.
    again = json.dumps(honest(unique("empty-type"))).encode()
    response = client.post("/submit", content=again, headers={"Content-Type": ""})
    assert response.status_code == 201, response.text
    bad = client.post("/submit", content=b'{"kind": ')
    assert bad.status_code == 422 and locs(bad) == [["body"]]


@pytest.mark.parametrize("encoding", ["gzip", "deflate, gzip", "br"])
def test_a_compressed_body_is_415_naming_the_encoding(client: TestClient, encoding: str) -> None:
    """Bodies are read as they come: a gzip body is refused for what it is, not as bad JSON."""
    before = count(client, ModelVersion)
    body = json.dumps(honest(unique("gz"))).encode()
    headers = {**JSON, "Content-Encoding": encoding}
    response = client.post("/submit", content=body, headers=headers)
    assert response.status_code == 415 and locs(response) == [["header", "Content-Encoding"]]
    assert count(client, ModelVersion) == before
    plain = client.post("/submit", content=body, headers={**JSON, "Content-Encoding": "identity"})
    assert plain.status_code == 201, plain.text


def test_json_suffix_media_types_are_json(client: TestClient) -> None:
    body = json.dumps(honest(unique("suffix")))
    response = client.post(
        "/submit", content=body, headers={"Content-Type": "application/vnd.srd+json"}
    )
    assert response.status_code == 201, response.text


@pytest.mark.parametrize(
    ("body", "field"),
    [
        ({"n_fish": "3"}, "n_fish"),
        ({"n_fish": True}, "n_fish"),
        ({"n_fish": 3.0}, "n_fish"),
        ({"rarity": "0.5"}, "rarity"),
        ({"n_fish": 3, "fine_tune": "yes"}, "fine_tune"),
        ({"n_fish": 3, "seed": "1"}, "seed"),
    ],
)
def test_auction_fields_are_typed_strictly(client: TestClient, body, field) -> None:
    before = count(client, Auction)
    response = client.post("/auctions", json=body, headers=ADMIN)
    assert response.status_code == 422
    assert ["body", field] in locs(response)
    assert count(client, Auction) == before


@pytest.mark.parametrize(
    ("params", "loc"),
    [
        ({"steps": "50"}, ["body", "params", "steps"]),
        ({"steps": 50.0}, ["body", "params", "steps"]),
        ({"srd": "yes"}, ["body", "params", "srd"]),
    ],
)
def test_job_params_are_typed_strictly(client: TestClient, params, loc) -> None:
    before = count(client, Job)
    response = client.post("/jobs", json={"kind": "fish", "params": params}, headers=ADMIN)
    assert response.status_code == 422
    assert loc in locs(response)
    assert count(client, Job) == before


@pytest.mark.parametrize(
    ("kind", "params", "stored"),
    [
        ("auction-study", {"rarities": "0.1, 0.5", "trials": 1}, {"rarities": [0.1, 0.5]}),
        ("auction-study", {"rarities": 0.5, "trials": 1}, {"rarities": [0.5]}),
        ("cheetah", {"backswing": "1,2", "trials": 1, "steps": 10}, {"backswing": [1, 2]}),
        ("fish", {"steps": 5, "no-srd": True}, {"srd": False}),
        ("fish", {"steps": 5, "no_srd": False}, {"srd": True}),
    ],
)
def test_job_params_take_the_command_lines_spellings(
    client: TestClient, kind: str, params: dict[str, Any], stored: dict[str, Any]
) -> None:
    """As the CLI's options: a list comma-separated or as one value, a flag by its negation."""
    created = client.post("/jobs", json={"kind": kind, "params": params}, headers=ADMIN)
    assert created.status_code == 202, created.text
    job_id = created.json()["job_id"]
    job = client.get(f"/jobs/{job_id}").json()
    assert {key: job["params"][key] for key in stored} == stored
    client.delete(f"/jobs/{job_id}", headers=ADMIN)


@pytest.mark.parametrize(
    ("params", "loc"),
    [
        ({"rarities": "0.1,x"}, ["body", "params", "rarities", 1]),
        # items no number parser should be handed: 4400 digits, a deep nest, an overflow
        ({"rarities": "1" * 4400}, ["body", "params", "rarities", 0]),
        ({"rarities": "0.5," + "[" * 50000 + "]" * 50000}, ["body", "params", "rarities", 1]),
        ({"rarities": "0.5,1e400"}, ["body", "params", "rarities", 1]),
        # named as sent: the negation, not the flag it negates
        ({"rarities": "0.1", "trials": 1, "no-screen": "yes"}, ["body", "params", "no-screen"]),
        ({"srd": True}, ["body", "params", "srd"]),  # not an option of this kind
    ],
)
def test_job_spellings_still_name_the_bad_field(client: TestClient, params, loc) -> None:
    before = count(client, Job)
    response = client.post("/jobs", json={"kind": "auction-study", "params": params}, headers=ADMIN)
    assert response.status_code == 422, response.text
    assert loc in locs(response)
    assert count(client, Job) == before


@pytest.mark.parametrize(
    "path", ["/models?limit=3&limit=5", "/auctions/1/rounds/current?wait=0&after=1&wait=5"]
)
def test_a_query_parameter_given_twice_is_refused(client: TestClient, path: str) -> None:
    """Which one counts would be a guess: the long poll's share once read the first ``wait``
    and the route the last, so one address could hold four times its share of long polls."""
    response = client.get(path)
    assert response.status_code == 400
    (item,) = response.json()["detail"]
    name = path.split("?")[1].split("&")[-1].split("=")[0]
    assert item["loc"] == ["query", name] and item["type"] == "duplicate_parameter"


def test_a_header_that_names_one_thing_given_twice_is_refused(client: TestClient) -> None:
    for name in ("Last-Event-ID", "Authorization"):
        headers = [(name, "1"), (name, "2")]
        response = client.get("/auctions/1/events", headers=headers)
        assert response.status_code == 400, response.text
        (item,) = response.json()["detail"]
        assert item["loc"] == ["header", name] and item["type"] == "duplicate_header"
    # The body's checks read the last Content-Type and the routes the first: 415 or 422
    # depending on their order.
    for types in (["text/plain", "application/json"], ["application/json", "text/plain"]):
        headers = [("Content-Type", value) for value in types]
        response = client.post("/submit", content=b"{}", headers=headers)
        assert response.status_code == 400, response.text
        (item,) = response.json()["detail"]
        assert item["loc"] == ["header", "Content-Type"] and item["type"] == "duplicate_header"


def test_a_long_parameter_name_is_named_by_its_start(client: TestClient) -> None:
    """Refusals name a parameter by its first 64 characters (an 8,000-character name had come
    back whole, twice, in a 16 KB answer)."""
    name = "a" * 2000
    for query in (f"{name}=1", f"{name}=1&{name}=2"):
        response = client.get(f"/models?{query}")
        assert response.status_code in (400, 422), response.text
        (item,) = response.json()["detail"]
        assert item["loc"] == ["query", "a" * 64 + "…"], item["loc"]
        assert len(item["msg"]) < 300 and "a" * 64 + "…" in item["msg"]


@pytest.mark.parametrize(
    ("path", "name"),
    [("/models?sttaus=held", "sttaus"), ("/auctions?limit=2&sort=old", "sort"),
     ("/healthz?verbose=1", "verbose")],
)  # fmt: skip
def test_a_query_parameter_the_path_does_not_take_is_422(
    client: TestClient, path: str, name: str
) -> None:
    """A misspelt filter would otherwise answer everything, as if none were asked."""
    response = client.get(path)
    assert response.status_code == 422, response.text
    (item,) = response.json()["detail"]
    assert item["loc"] == ["query", name] and item["type"] == "unknown_parameter"
    assert client.get("/?utm_source=mail").status_code == 200  # pages take any


def test_a_trailing_slash_is_404_not_a_redirect_to_the_host_header(client: TestClient) -> None:
    response = client.get("/models/", headers={"Host": "evil.example"}, follow_redirects=False)
    assert response.status_code == 404 and "location" not in response.headers


def test_a_websocket_anywhere_but_the_round_socket_is_a_json_404(client: TestClient) -> None:
    for path in ("/models/1", "/auctions/1/events", "/nowhere"):
        with pytest.raises(WebSocketDenialResponse) as denied, client.websocket_connect(path):
            pass
        assert denied.value.status_code == 404
        assert denied.value.headers["content-type"] == "application/json"
        assert denied.value.headers["x-frame-options"] == "DENY"
        assert "/auctions/{id}/rounds/socket" in denied.value.json()["detail"][0]["msg"]


@pytest.mark.parametrize("raw", ["1.0", "1%20", "%201", "+1", "1e0", "0x1", "%EF%BC%91", "1_0"])
def test_path_ids_are_digits_only(client: TestClient, raw: str) -> None:
    for prefix, name in (
        ("/jobs/", "job_id"),
        ("/models/", "model_id"),
        ("/auctions/", "auction_id"),
    ):
        response = client.get(prefix + raw)
        assert response.status_code == 422, (prefix, raw, response.text)
        assert locs(response) == [["path", name]]
    # A round too (its PUT would otherwise take "1.0" or "1_0" for a round).
    headers = {**JSON, "Authorization": "Bearer srdp_not-a-token"}
    upload = client.put(f"/auctions/1/rounds/{raw}/models/1", content=b"{}", headers=headers)
    assert upload.status_code == 422 and ["path", "round"] in locs(upload), upload.text


@pytest.mark.parametrize("raw", ["1.0", "%2B1", "1_0", "%201%20", "-1"])
def test_integer_query_parameters_are_digits_only(client: TestClient, raw: str) -> None:
    """As path ids: the reviews' cursor and a long poll's last round handled."""
    for path, name in (
        (f"/reviews?cursor={raw}", "cursor"),
        (f"/auctions/1/rounds/current?after={raw}", "after"),
        (f"/auctions?cursor={raw}", "cursor"),
    ):
        response = client.get(path, headers=ADMIN)
        assert response.status_code == 422, (path, response.text)
        assert locs(response) == [["query", name]]
        assert "whole number written in digits" in response.text


@pytest.mark.parametrize("raw", ["1_0", "%2B1", "%201", "0x1", ".5", "nan", "01"])
def test_a_long_polls_seconds_are_a_json_number(client: TestClient, raw: str) -> None:
    response = client.get(f"/auctions/1/rounds/current?wait={raw}")
    assert response.status_code == 422, response.text
    assert locs(response) == [["query", "wait"]]
    assert "JSON number" in response.text
    for good in ("0", "0.25", "1e-05"):  # as clients print them (404: no such auction)
        assert client.get(f"/auctions/987654/rounds/current?wait={good}").status_code == 404


def test_artifact_name_with_a_null_byte_is_404(client: TestClient) -> None:
    created = client.post("/jobs", json={"kind": "fish", "params": {"steps": 5}}, headers=ADMIN)
    job_id = created.json()["job_id"]
    for name in ("a%00b", "%00"):
        response = client.get(f"/jobs/{job_id}/artifacts/{name}")
        assert response.status_code == 404
        assert locs(response) == [["path", "name"]]


def test_405_names_every_method_of_the_path(client: TestClient) -> None:
    for method, path, allowed in (
        ("OPTIONS", "/jobs/1", "DELETE, GET, HEAD"),
        ("PUT", "/jobs/1", "DELETE, GET, HEAD"),
        ("GET", "/submit", "POST"),
        ("OPTIONS", "/openapi.json", "GET, HEAD"),  # the app's own route too
    ):
        response = client.request(method, path)
        assert response.status_code == 405
        assert response.headers["allow"] == allowed


def _careful(raw: bytes) -> Any:
    """The body as the careful pass alone judges it (the fast pass must agree)."""
    from server.api.body import _Pairs, _resolve

    return _resolve(json.loads(raw.decode(), object_pairs_hook=_Pairs), (), 0)


@pytest.mark.parametrize(
    "text",
    [
        '{"a": 1, "b": {"c": [1, 2, {"d": null}]}, "e": "x\\"[{"}',
        '{"a": {"b": 1, "b": 2}}',
        '[{"x": 1}, {"x": 1, "x": 1}]',
        '{"a": [NaN]}',
        '{"a": {"b": -Infinity}}',
        '{"a": Infinity}',
        '{"a": [1, 1e999]}',
        '{"a": {"b": -1E+400}}',
        '{"a": 1' + "0" * 320 + ".5}",
        '[1e308, 1.7976931348623157e308, 1e-400, 0.5e0010, "e000"]',
        "[" * 32 + "]" * 32,
        "[" * 33 + "]" * 33,
        "[" * 32 + "1" + "]" * 32,
        "[" * 33 + "1" + "]" * 33,
        '{"k": ' * 33 + "1" + "}" * 33,
        '{"k": ' * 31 + '"[[[[[[[[[[[[[[[["' + "}" * 31,
        '"just a string"',
        "3.5",
    ],
)
def test_the_fast_strict_json_pass_agrees_with_the_careful_one(text: str) -> None:
    """``parse_strict_json`` parses in one pass and only goes back to the careful pass (which
    names the location) when something is wrong: the same value, or the same refusal."""
    from server.api.body import BodyRefusedError, parse_strict_json

    raw = text.encode()
    try:
        expected: Any = ("value", _careful(raw))
    except BodyRefusedError as exc:
        expected = ("refused", exc.status, exc.loc, exc.kind)
    try:
        got: Any = ("value", parse_strict_json(raw))
    except BodyRefusedError as exc:
        got = ("refused", exc.status, exc.loc, exc.kind)
    assert got == expected
    if got[0] == "value":
        assert json.dumps(got[1]) == json.dumps(expected[1])


@pytest.mark.parametrize("name", [".", "..", "...", "-", "--", "_", "-_-", "._."])
def test_a_name_of_separators_only_is_refused_naming_the_field(
    client: TestClient, name: str
) -> None:
    """'.' and '..' are path segments (GET /participants/.. would name another path), and a
    name of separators only reads as nothing: '-', '--' and '_' would be told apart by their
    lengths alone."""
    before = count(client, ModelVersion)
    answer = client.post("/submit", json=honest(name))
    assert answer.status_code == 422
    (item,) = answer.json()["detail"]
    assert item["loc"] == ["body", "participant"] and item["type"] == "bad_name"
    assert count(client, ModelVersion) == before
    assert client.post("/submit", json=honest(unique("a.b"))).status_code == 201


def test_a_submission_the_screener_cannot_judge_is_503_at_the_server(
    client: TestClient, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The screening process died under it: the body was fine, so the 503 names the server
    and says when to retry; nothing is stored."""
    from server.screening.pool import ScreenerUnavailableError

    async def gone(*_args: Any, **_kwargs: Any) -> Any:
        raise ScreenerUnavailableError("the screening process exited; retry shortly")

    services = client.app.state.services  # type: ignore[attr-defined]
    monkeypatch.setattr(services.screening, "verdict", gone)
    before = count(client, ModelVersion)
    answer = client.post("/submit", json=honest(unique("unjudged")))
    assert answer.status_code == 503, answer.text
    (item,) = answer.json()["detail"]
    assert item["loc"] == ["server"] and item["type"] == "screener_unavailable"
    assert answer.headers["retry-after"] == "2"
    assert count(client, ModelVersion) == before


@pytest.mark.parametrize(
    "raw",
    [
        b'["' + b'\\"' * 128_000,  # an open string of escaped quotes: every quote restarted a scan
        b'["' + b'\\"' * 60_000 + b'"]',
        b'["' + b'\\"' * 100_000 + b'\\\n"]',  # an escaped line break among them
        b'{"d": "' + (b"1" * 4300 + b" ") * 59 + b'"}',  # runs of digits just short of too long
    ],
)
def test_checking_a_body_costs_time_in_proportion_to_it(raw: bytes) -> None:
    """The checks before the parser are linear: a 256 KB body of these took minutes of the
    event loop (quadratic patterns), now milliseconds; 5 s leaves a hundredfold margin."""
    from server.api.body import BodyRefusedError, parse_strict_json

    started = time.perf_counter()
    with contextlib.suppress(BodyRefusedError):
        parse_strict_json(raw)
    assert time.perf_counter() - started < 5


def test_blanking_secrets_in_a_logged_query_costs_time_in_proportion_to_it() -> None:
    from server.api.hardening import redact_query

    started = time.perf_counter()  # 60,000 characters without "=" had taken 42 s
    assert redact_query("/healthz?" + "a" * 60_000) == "/healthz?" + "a" * 60_000
    assert time.perf_counter() - started < 5
    cases = {  # what the blanking does, unchanged
        "/x?token=abc&b=1": "/x?token=***&b=1",
        "/x?a?token=abc": "/x?a?token=***",
        "/x?%74oken=abc&=v&k": "/x?%74oken=***&=v&k",
        "/x?a=b=c&pw=1&pwd=2": "/x?a=b=c&pw=***&pwd=2",
        "/x?q=Bearer%20srdp_x": "/x?***",
        "/x?=token=abc&a?=key=1": "/x?=token=***&a?=key=***",
    }
    assert {path: redact_query(path) for path in cases} == cases


def test_a_long_query_is_414_and_a_long_path_is_cut_in_the_access_log(client: TestClient) -> None:
    """No route reads a query of kilobytes: one over 4096 bytes is refused before it is read
    (a 60 KB query cost the event loop 90 ms), and an access log line shows at most 1024
    characters of a path (a line of 60 KB had let one address write 3 MB of log a second)."""
    import logging

    from server.api.hardening import RedactQueryFilter

    response = client.get("/models?" + "&".join(["a=1"] * 1_400))
    assert response.status_code == 414, response.text
    (item,) = response.json()["detail"]
    assert item["loc"] == ["query"] and "longer than 4096 bytes" in item["msg"]
    assert client.get("/models?" + "&".join(["limit=1"] * 500)).status_code == 400  # 4 KB
    path = "/nowhere/" + "x" * 50_000 + "?token=srdp_secret"
    record = logging.LogRecord("uvicorn.access", 20, "", 0, "%s %s %s", ("1", "GET", path), None)
    assert RedactQueryFilter().filter(record)
    logged = record.getMessage()
    assert len(logged) < 1100 and logged.endswith("…") and "srdp_secret" not in logged


def test_a_write_another_site_sent_is_refused(client: TestClient) -> None:
    """A page of another site can make its visitors' browsers POST a manifest without a
    preflight (an untyped body): browsers mark such a request ``Sec-Fetch-Site: cross-site``,
    and the server refuses it, so it registers nobody and spends no visitor's quota."""
    before = count(client, ModelVersion)
    body = json.dumps(honest(unique("cross"))).encode()
    refused = client.post("/submit", content=body, headers={"Sec-Fetch-Site": "cross-site"})
    assert refused.status_code == 403, refused.text
    (item,) = refused.json()["detail"]
    assert item["loc"] == ["header", "Sec-Fetch-Site"] and item["type"] == "cross_site"
    assert count(client, ModelVersion) == before
    assert client.get("/models", headers={"Sec-Fetch-Site": "cross-site"}).status_code == 200
    for site in ("same-origin", "none"):  # the web view, a typed URL
        again = json.dumps(honest(unique("site"))).encode()
        at_the_server = {"Sec-Fetch-Site": site, "Host": "127.0.0.1:8000"}
        answer = client.post("/submit", content=again, headers=at_the_server)
        assert answer.status_code == 201, answer.text
    # a sibling subdomain's page (or another port's) is another site's too; and an older
    # browser that sends no Sec-Fetch-Site is judged by its Origin
    for headers, loc in (
        ({"Sec-Fetch-Site": "same-site"}, "Sec-Fetch-Site"),
        ({"Origin": "https://evil.example"}, "Origin"),
        ({"Origin": "null"}, "Origin"),
    ):
        refused = client.post("/submit", content=body, headers=headers)
        assert refused.status_code == 403 and locs(refused) == [["header", loc]], refused.text
    assert count(client, ModelVersion) == before + 2
    own = json.dumps(honest(unique("own"))).encode()
    own_page = {"Origin": "http://localhost:8000", "Host": "localhost"}
    answer = client.post("/submit", content=own, headers=own_page)
    assert answer.status_code == 201, answer.text  # its own page, whatever the port


def test_a_page_at_a_host_name_the_server_does_not_answer_pages_at_writes_nothing(
    client: TestClient,
) -> None:
    """DNS rebinding: another site's name made to resolve to the server makes that site's page
    same-origin with it (``Sec-Fetch-Site: same-origin``, ``Origin`` naming the ``Host``), so
    the cross-site rule lets its writes through. A page's write is taken at an IP address,
    ``localhost`` and the names ``SRD_ALLOWED_HOSTS`` lists only; scripts, which send no
    ``Origin``, are not concerned, nor are reads."""
    before = count(client, ModelVersion)
    body = json.dumps(honest(unique("rebound"))).encode()
    rebound = {"Host": "attacker.example:8000", "Origin": "http://attacker.example:8000"}
    for marks in ({"Sec-Fetch-Site": "same-origin"}, {}):  # a browser today, an older one
        refused = client.post("/submit", content=body, headers={**rebound, **marks})
        assert refused.status_code == 403, refused.text
        (item,) = refused.json()["detail"]
        assert item["loc"] == ["header", "Host"] and item["type"] == "host_not_allowed"
        assert "'attacker.example'" in item["msg"] and "SRD_ALLOWED_HOSTS" in item["msg"]
    assert count(client, ModelVersion) == before
    page = {**rebound, "Sec-Fetch-Site": "same-origin"}
    assert client.get("/models", headers=page).status_code == 200  # reading is not writing
    typed = {"Host": "attacker.example", "Sec-Fetch-Site": "none"}  # no page sent it
    assert client.post("/submit", content=body, headers=typed).status_code == 201
    for name in ("[::1]", "10.0.0.7", "app.localhost", "localhost."):
        at = {"Host": name, "Origin": f"http://{name}", "Sec-Fetch-Site": "same-origin"}
        again = json.dumps(honest(unique("addressed"))).encode()
        answer = client.post("/submit", content=again, headers=at)
        assert answer.status_code == 201, (name, answer.text)


def test_the_host_names_srd_allowed_hosts_lists_take_pages_writes(tmp_path: Path) -> None:
    """A name the setting lists (``*.`` for every name under it) takes its pages' writes;
    another is refused as before; an entry that is not a host name stops the settings."""
    settings = make_settings(
        f"sqlite:///{tmp_path / 'srd.db'}",
        tmp_path / "data",
        allowed_hosts="Auction.Example, *.example.org",
    )
    with TestClient(create_app(settings)) as listed:
        for name, status in (
            ("auction.example", 201),
            ("a.b.example.org", 201),
            ("example.org", 403),  # "*." names what is under it only
            ("auction.example.evil", 403),
        ):
            at = {"Host": name, "Origin": f"https://{name}", "Sec-Fetch-Site": "same-origin"}
            again = json.dumps(honest(unique("listed"))).encode()
            assert listed.post("/submit", content=again, headers=at).status_code == status, name
    with pytest.raises(ValueError, match=re.escape("'https://auction.example' is not a host name")):
        make_settings("sqlite://", tmp_path, allowed_hosts="https://auction.example")
