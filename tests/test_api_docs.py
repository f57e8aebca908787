"""The API's description against the server it describes.

REST: every route's statuses are in /openapi.json as listed here, and real requests that make
each refusal (401, 404, 409, 413, 415, 422, 429, 503) and the 201 of a ready upload get a status
the document lists for that route, with a body its schema accepts. Docs: /docs and /redoc load
only from this server (their HTML names no other host, and a headless Chromium that renders them
requests nothing elsewhere). WebSocket: service/asyncapi.yaml parses, its client messages carry
exactly the constraints of service/protocol.py's models, every message a live session sends
validates against its schemas, and its message types and error codes are the ones the server's
code names.
"""

from __future__ import annotations

import ast
import json
import re
import struct
import time
import typing
from contextlib import contextmanager
from pathlib import Path

import httpx
import jsonschema
import numpy as np
import pytest
import yaml
from fastapi.testclient import TestClient
from websockets.sync.client import connect

from models.data import load_motion, select
from models.registry import load_models
from models.settings import get_settings
from service import protocol as P
from service.app import create_app
from service.routes_docs import ASSET_TYPES, ASYNCAPI_FILE
from service.settings import ServiceSettings

from .clips import frames_json
from .live_server import UPLOAD_TIMEOUT_S, live_server
from .test_viewer import devtools_page, need_chromium

SERVICE_DIR = Path(__file__).resolve().parents[1] / "service"
TOKEN, SLOW = "tok-docs", "tok-slow"  # SLOW: one request per 100 s, so its second is refused
UPLOAD_LIMIT = 4 * 1024 * 1024
# what each route answers: the contract the description must state (and the code keeps)
ROUTES: dict[tuple[str, str], set[int]] = {
    ("get", "/healthz"): {200},
    ("get", "/readyz"): {200, 503},
    ("get", "/metrics"): {200, 503},
    ("get", "/v1/models"): {200, 401, 429, 503},
    ("get", "/v1/styles"): {200, 401, 422, 429, 503},
    ("post", "/v1/styles"): {201, 202, 401, 409, 413, 415, 422, 429, 503, 507},
    ("get", "/v1/styles/{style_id}"): {200, 401, 404, 422, 429, 503},
    ("delete", "/v1/styles/{style_id}"): {204, 401, 404, 409, 422, 429, 503},
    ("get", "/v1/jobs/{job_id}"): {200, 401, 404, 422, 429, 503},
    ("get", "/v1/demo/clip"): {200},
    ("post", "/v1/skeletons"): {200, 401, 422, 429, 503},
}
ASYNCAPI = yaml.safe_load(ASYNCAPI_FILE.read_text())
SCHEMAS = ASYNCAPI["components"]["schemas"]
CLIENT_SCHEMAS = {"start": "Start", "frame": "Frame", "control": "Control", "style": "SetStyle", "reset": "Reset"}
CLIENT_SCHEMAS |= {"end": "End", "crowd": "CrowdStart", "join": "Join", "leave": "Leave"}
SERVER_SCHEMAS = {"started": "Started", "frame": "FrameReply", "style_set": "StyleSet", "reset_done": "ResetDone"}
SERVER_SCHEMAS |= {"ended": "Ended", "snapshot": "Snapshot", "error": "Error"}
SERVER_SCHEMAS |= {"crowd_started": "CrowdStarted", "joined": "Joined", "left": "Left"}


@pytest.fixture(scope="module")
def models():
    return load_models(get_settings().weights_dir)


@pytest.fixture(scope="module")
def server(models, tmp_path_factory):
    with live_server(
        models,
        styles_dir=tmp_path_factory.mktemp("styles"),
        api_tokens=[TOKEN, SLOW],
        token_limits={SLOW: {"requests_per_s": 0.01, "burst_s": 1}},
        upload_max_bytes=UPLOAD_LIMIT,
        snapshot_every=4,
        idle_timeout_s=60,
    ) as (base, _app):
        yield base


@pytest.fixture(scope="module")
def openapi(server) -> dict:
    return httpx.get(f"{server}/openapi.json").json()


def response_validator(doc: dict, method: str, path: str, status: int) -> jsonschema.Draft202012Validator | None:
    """A validator of the JSON body the document gives this route and status (None: no JSON body)."""
    reply = doc["paths"][path][method]["responses"][str(status)]
    schema = reply.get("content", {}).get("application/json", {}).get("schema")
    if schema is None:
        return None
    return jsonschema.Draft202012Validator({**schema, "components": doc["components"]})


def test_every_route_documents_its_statuses(openapi):
    documented = {
        (method, path): {int(s) for s in op["responses"]}
        for path, ops in openapi["paths"].items()
        for method, op in ops.items()
    }
    assert documented == ROUTES
    for (method, path), statuses in ROUTES.items():
        op = openapi["paths"][path][method]
        assert op.get("summary"), (method, path)
        for status in statuses - {200, 201, 202, 204}:
            reply = op["responses"][str(status)]
            assert reply["description"] not in ("", "Error"), (method, path, status)
            schema = reply["content"]["application/json"]["schema"]
            # every refusal is an ErrorBody (or, for a rig, the ErrorBody with `missing`; readiness: Health)
            assert schema["$ref"].rsplit("/", 1)[1] in {"ErrorBody", "RigProblem", "Health"}, (method, path, status)
    assert "HTTPValidationError" not in json.dumps(openapi)  # 422s are described as they are answered
    for ref in set(re.findall(r'"\$ref": "([^"]+)"', json.dumps(openapi))):  # every reference resolves
        node = openapi
        for part in ref.removeprefix("#/").split("/"):
            assert isinstance(node, dict) and part in node, f"{ref} does not resolve"
            node = node[part]
    upload = openapi["paths"]["/v1/styles"]["post"]
    assert set(upload["requestBody"]["content"]) == {"application/json", "multipart/form-data"}
    assert set(upload["responses"]["429"]["headers"]) == {"Retry-After"}


def check_reply(doc: dict, method: str, path: str, reply: httpx.Response, status: int, code: str | None = None) -> None:
    assert reply.status_code == status, reply.text
    assert status in ROUTES[(method, path)], f"{method} {path} answered {status}, which is not documented"
    validator = response_validator(doc, method, path, status)
    if validator is not None:
        validator.validate(reply.json())
    if code is not None:
        assert reply.json()["code"] == code, reply.text


def test_real_replies_are_documented_with_their_bodies(server, openapi, index):
    doc, ok, slow = openapi, {"Authorization": f"Bearer {TOKEN}"}, {"Authorization": f"Bearer {SLOW}"}
    # a fresh clone's server compiles kernels on first use (a rig's adapter, an upload's fit), and
    # a loaded machine stretches that past httpx's 5 s default: wait on the reply, not a clock
    http = httpx.Client(timeout=UPLOAD_TIMEOUT_S)
    styles = f"{server}/v1/styles"
    check_reply(doc, "get", "/healthz", http.get(f"{server}/healthz"), 200)
    check_reply(doc, "get", "/readyz", http.get(f"{server}/readyz"), 200)
    check_reply(doc, "get", "/v1/models", http.get(f"{server}/v1/models"), 401, "unauthorized")
    check_reply(doc, "get", "/v1/models", http.get(f"{server}/v1/models", headers=ok), 200)
    check_reply(doc, "get", "/v1/styles", http.get(styles, headers=slow), 200)
    limited = http.get(styles, headers=slow)
    check_reply(doc, "get", "/v1/styles", limited, 429, "rate_limited")
    assert int(limited.headers["retry-after"]) >= 1
    check_reply(doc, "get", "/v1/styles/{style_id}", http.get(f"{styles}/lti.elderly", headers=ok), 200)
    check_reply(doc, "get", "/v1/styles/{style_id}", http.get(f"{styles}/lti.nope", headers=ok), 404, "unknown_style")
    trained = http.delete(f"{styles}/lti.elderly", headers=ok)
    check_reply(doc, "delete", "/v1/styles/{style_id}", trained, 409, "trained_style")
    check_reply(doc, "get", "/v1/jobs/{job_id}", http.get(f"{server}/v1/jobs/nope", headers=ok), 404, "unknown_job")

    text = http.post(styles, content=b"walk", headers={**ok, "Content-Type": "text/plain"})
    check_reply(doc, "post", "/v1/styles", text, 415, "unsupported_media_type")
    big = http.post(styles, content=b"x" * (UPLOAD_LIMIT + 1), headers={**ok, "Content-Type": "application/json"})
    check_reply(doc, "post", "/v1/styles", big, 413, "too_large")
    walk = frames_json(
        load_motion(select(index, dataset="bandai-namco-2", style="normal", content="walk", split="val")[0]).slice(
            0, 90
        )
    )
    body = {"name": "Bad Name", "model": "lpn", "frames": walk, "fps": 30}
    named = http.post(styles, json=body, headers=ok)
    check_reply(doc, "post", "/v1/styles", named, 422, "bad_name")
    maybe = http.post(f"{styles}?fine_tune=maybe", json=body, headers=ok)  # FastAPI's own validation
    check_reply(doc, "post", "/v1/styles", maybe, 422, "bad_request")
    assert "fine_tune" in maybe.json()["message"]
    made = http.post(styles, json={**body, "name": "docs-walk"}, headers=ok)
    check_reply(doc, "post", "/v1/styles", made, 201)
    assert made.json()["style"]["status"] == "ready"
    again = http.post(styles, json={**body, "name": "docs-walk"}, headers=ok)
    check_reply(doc, "post", "/v1/styles", again, 409, "style_exists")
    gone = http.delete(f"{styles}/lpn.docs-walk", headers=ok)
    check_reply(doc, "delete", "/v1/styles/{style_id}", gone, 204)

    rigs = f"{server}/v1/skeletons"
    check_reply(doc, "post", "/v1/skeletons", http.post(rigs, json={"skeleton": "ue5"}, headers=ok), 200)
    check_reply(doc, "post", "/v1/skeletons", http.post(rigs, json={"skeleton": "ue5"}), 401, "unauthorized")
    neither = http.post(rigs, json={}, headers=ok)
    check_reply(doc, "post", "/v1/skeletons", neither, 422, "bad_request")
    extra = http.post(rigs, json={"skeleton": "ue5", "colour": "red"}, headers=ok)
    check_reply(doc, "post", "/v1/skeletons", extra, 422, "bad_request")
    assert "colour" in extra.json()["message"]
    http.close()


def test_a_server_that_is_not_up_answers_503_as_documented(models):
    """Before its lifespan has run (no runtime yet), readiness and the routes that need the runtime
    answer 503 in their documented shapes."""
    app = create_app(ServiceSettings(), models={})
    client = TestClient(app)  # not entered: the lifespan does not run
    doc = app.openapi()
    ready = client.get("/readyz")
    assert ready.status_code == 503 and ready.json() == {"status": "loading"}
    response_validator(doc, "get", "/readyz", 503).validate(ready.json())
    for path in ("/metrics", "/v1/models", "/v1/styles"):
        reply = client.get(path)
        assert reply.status_code == 503 and reply.json()["code"] == "starting_up", (path, reply.text)
        assert 503 in ROUTES[("get", path)]
        response_validator(doc, "get", path, 503).validate(reply.json())


# ---- the docs pages -------------------------------------------------------------------------


def page_urls(html: str) -> list[str]:
    return re.findall(r"""(?:src|href|url|spec-url)\s*[=:]\s*["']([^"']+)["']""", html)


@pytest.mark.parametrize("page", ["/docs", "/redoc"])
def test_docs_pages_load_everything_from_this_server(server, page):
    html = httpx.get(f"{server}{page}").text
    assert not re.search(r"(?i)(https?:)?//[a-z0-9]", html), f"{page} names another host: {html}"
    urls = page_urls(html)
    assert "/openapi.json" in urls and any(u.startswith("/docs/assets/") for u in urls), urls
    for url in urls:
        reply = httpx.get(f"{server}{url}")
        assert reply.status_code == 200, url
        if url.startswith("/docs/assets/"):
            name = url.rsplit("/", 1)[1]
            assert reply.headers["content-type"].startswith(ASSET_TYPES[name]) and len(reply.content) > 1000, url
    assert httpx.get(f"{server}/docs/assets/..%2Fcore.py").status_code == 404
    assert httpx.get(f"{server}/docs/assets/core.py").status_code == 404


def test_asyncapi_document_is_served_and_linked(server, openapi):
    reply = httpx.get(f"{server}/asyncapi.yaml")
    assert reply.status_code == 200 and reply.headers["content-type"].startswith("application/yaml")
    assert yaml.safe_load(reply.text) == ASYNCAPI
    assert "](asyncapi.yaml)" in openapi["info"]["description"]


def test_docs_pages_render_offline_in_chromium(server, openapi, tmp_path):
    """Rendered by a real browser, Swagger UI shows every operation and the AsyncAPI link, ReDoc
    every operation, and neither page requests anything from another origin."""
    need_chromium()
    operations = sum(len(ops) for ops in openapi["paths"].values())
    requested: list[str] = []
    with devtools_page(tmp_path) as page:
        page.handlers["Network.requestWillBeSent"] = lambda p: requested.append(p["request"]["url"])
        page.call("Network.enable")
        page.call("Page.navigate", url=f"{server}/docs")
        page.wait_for(f"document.querySelectorAll('.opblock').length === {operations}", "Swagger UI did not render")
        assert page.js("!!document.querySelector('a[href=\"asyncapi.yaml\"]')"), "no AsyncAPI link on /docs"
        page.call("Page.navigate", url=f"{server}/redoc")
        page.wait_for(
            f"document.querySelectorAll('[data-section-id^=\"operation/\"]').length === {operations}",
            "ReDoc did not render",
        )
    assert requested and all(u.startswith(server) or u.startswith(("data:", "blob:")) for u in requested), [
        u for u in requested if not u.startswith(server)
    ]


# ---- the AsyncAPI document against the server -----------------------------------------------


def canonical(schema):
    """A JSON schema with its words (title, description, examples) left out, and pydantic's
    `anyOf [X, null]` written as X with `type: [..., null]`, as the document writes it."""
    if isinstance(schema, list):
        return [canonical(s) for s in schema]
    if not isinstance(schema, dict):
        return schema
    out = {k: canonical(v) for k, v in schema.items() if k not in ("title", "description", "examples")}
    branches = out.get("anyOf")
    if branches and len(branches) == 2 and {"type": "null"} in branches:
        (other,) = [b for b in branches if b != {"type": "null"}]
        out = {**{k: v for k, v in out.items() if k != "anyOf"}, **other, "type": [other["type"], "null"]}
        if "enum" in other:
            out["enum"] = [*other["enum"], None]
    if isinstance(out.get("type"), list):
        out["type"] = sorted(out["type"])
    for key in ("required", "enum"):
        if key in out:
            out[key] = sorted(out[key], key=repr)
    return out


def inline(schema, prefix: str, defs: dict):
    """`schema` with every `$ref` under `prefix` replaced by the schema it names (and `$defs` gone)."""
    if isinstance(schema, list):
        return [inline(s, prefix, defs) for s in schema]
    if not isinstance(schema, dict):
        return schema
    ref = schema.get("$ref", "")
    if ref.startswith(prefix):
        return inline(defs[ref[len(prefix) :]], prefix, defs)
    return {k: inline(v, prefix, defs) for k, v in schema.items() if k != "$defs"}


def client_models() -> dict[str, type]:
    union = typing.get_args(P.ClientMessage)[0]
    return {typing.get_args(m.model_fields["type"].annotation)[0]: m for m in typing.get_args(union)}


def validator(name: str) -> jsonschema.Draft7Validator:
    return jsonschema.Draft7Validator({"$ref": f"#/components/schemas/{name}", "components": ASYNCAPI["components"]})


def test_asyncapi_client_messages_are_the_protocol_models():
    models = client_models()
    assert set(models) == set(CLIENT_SCHEMAS), "a client message is missing from the AsyncAPI document, or extra"
    for kind, model in models.items():
        schema = model.model_json_schema()  # nested models as pydantic's $defs, the document's as components
        assert canonical(inline(SCHEMAS[CLIENT_SCHEMAS[kind]], "#/components/schemas/", SCHEMAS)) == canonical(
            inline(schema, "#/$defs/", schema.get("$defs", {}))
        ), kind
    received = [m for op in ASYNCAPI["operations"].values() if op["action"] == "receive" for m in op["messages"]]
    names = {ref["$ref"].rsplit("/", 1)[1] for ref in received}
    assert names == set(models) | {"binaryFrame", "binaryTick"}
    for name, message in ASYNCAPI["components"]["messages"].items():
        for example in message.get("examples", []):
            schema = message["payload"]["$ref"].rsplit("/", 1)[1]
            validator(schema).validate(example["payload"])
            if schema in CLIENT_SCHEMAS.values():  # and the server reads it as that message
                assert type(P.parse_text(json.dumps(example["payload"]))).__name__ == schema, name


def protocol_error_codes() -> set[str]:
    """Every code the server's code gives a `ProtocolError`: the string constants passed to it,
    the two `parse_text` chooses between, and the skeleton codes `rig_error` maps to."""
    codes = set()
    for path in SERVICE_DIR.glob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if (
                isinstance(node, ast.Call)
                and getattr(node.func, "attr", getattr(node.func, "id", "")) == "ProtocolError"
            ):
                first = node.args[0]
                if isinstance(first, ast.Constant):
                    codes.add(first.value)
    parse_text = (SERVICE_DIR / "protocol.py").read_text().split("def parse_text", 1)[1].split("\ndef ", 1)[0]
    assert '"bad_json" if' in parse_text and 'else "bad_message"' in parse_text  # what the scan cannot see
    return codes | {"bad_json", "bad_message"}


def server_message_types() -> set[str]:
    """The `type` of every message dict the server's code builds (dict literals with a string
    `type`, leaving out JSON-schema type names and ASGI event and scope types)."""
    schema_words = {"object", "string", "integer", "number", "boolean", "array", "null", "http", "websocket"}
    found = set()
    for path in SERVICE_DIR.glob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Dict):
                for key, value in zip(node.keys, node.values, strict=True):
                    if isinstance(key, ast.Constant) and key.value == "type" and isinstance(value, ast.Constant):
                        if isinstance(value.value, str) and value.value not in schema_words and "." not in value.value:
                            found.add(value.value)
    return found


def test_asyncapi_names_every_message_and_error_code_the_server_has():
    assert server_message_types() == set(SERVER_SCHEMAS)
    for kind, name in SERVER_SCHEMAS.items():
        assert SCHEMAS[name]["properties"]["type"]["const"] == kind
    assert set(SCHEMAS["Error"]["properties"]["code"]["enum"]) == protocol_error_codes()
    sent = [m for op in ASYNCAPI["operations"].values() for m in op.get("reply", {}).get("messages", [])]
    sent += [m for op in ASYNCAPI["operations"].values() if op["action"] == "send" for m in op["messages"]]
    payloads = {ASYNCAPI["channels"]["stream"]["messages"][r["$ref"].rsplit("/", 1)[1]]["$ref"] for r in sent}
    schemas = {ASYNCAPI["components"]["messages"][p.rsplit("/", 1)[1]]["payload"]["$ref"] for p in payloads}
    assert {s.rsplit("/", 1)[1] for s in schemas} == set(SERVER_SCHEMAS.values()) | {"BinaryFrame"}
    layout = ASYNCAPI["components"]["messages"]["binaryFrame"]["x-binary-layout"]
    assert layout["header_bytes"] == P.BINARY_HEADER.size
    assert [f["offset"] for f in layout["fields"]] == [0, 4, 6, 8, 20]


@contextmanager
def resumed(url: str, token: str, check):
    """A connection that resumed session `token`, and its `started`; until the server has seen the
    old connection close, the answer is `session_in_use` (a fatal error): try again."""
    deadline = time.monotonic() + 10
    while True:
        with connect(url) as ws:
            ws.send(json.dumps({"type": "start", "model": "lti", "style": "elderly", "resume_token": token}))
            answer = check(ws.recv(timeout=30))
            if answer["type"] == "started":
                yield ws, answer
                return
        assert answer["code"] == "session_in_use" and time.monotonic() < deadline, answer
        time.sleep(0.05)


def test_every_message_a_live_session_sends_matches_its_schema(server, bn_walk):
    """A session through start, frames (snapshot acks on), a style change, a bad frame, text that
    is not JSON, a reset and end; a resumed one (with `last_frame`); a retargeted rig; and a
    binary session whose reply has the documented size."""
    url = server.replace("http", "ws") + f"/v1/stream?token={TOKEN}"
    root, rot = bn_walk.translations[:12, 1], bn_walk.rotations[:12]
    seen: dict[str, int] = {}

    def check(raw) -> dict:
        message = json.loads(raw)
        validator(SERVER_SCHEMAS[message["type"]]).validate(message)
        seen[message["type"]] = seen.get(message["type"], 0) + 1
        return message

    def frame(i: int) -> str:
        return json.dumps({"type": "frame", "seq": i, "root": root[i].tolist(), "rotations": rot[i].tolist()})

    with connect(url) as ws:
        ws.send(json.dumps({"type": "start", "model": "lti", "style": "elderly", "snapshot_acks": True}))
        token = check(ws.recv(timeout=30))["resume_token"]
        for i in range(8):
            ws.send(frame(i))
            while check(ws.recv(timeout=30))["type"] != "frame":
                pass
        while "snapshot" not in seen:  # the ack of the snapshot after frame 3 (or 7)
            check(ws.recv(timeout=30))
    with resumed(url, token, check) as (ws, started):
        assert started["last_seq"] is not None and started["last_frame"]["seq"] == started["last_seq"]
        ws.send(json.dumps({"type": "style", "style": "exhausted", "transition_frames": 5}))
        check(ws.recv(timeout=30))
        ws.send(json.dumps({"type": "frame", "seq": 9, "root": [0, 90, 0], "rotations": [[0, 0, 0, 1]]}))
        assert check(ws.recv(timeout=30))["seq"] == 9  # a bad_frame error for that frame
        ws.send("{not json")
        assert check(ws.recv(timeout=30))["code"] == "bad_json"
        ws.send(json.dumps({"type": "reset"}))
        check(ws.recv(timeout=30))
        ws.send(frame(10))
        check(ws.recv(timeout=30))
        ws.send(json.dumps({"type": "end"}))
        check(ws.recv(timeout=30))
    with connect(url) as ws:  # a preset rig the server retargets: `rig` carries the mapping's report
        ws.send(json.dumps({"type": "start", "model": "lti", "style": "elderly", "skeleton": "ue5"}))
        started = check(ws.recv(timeout=30))
        assert started["rig"]["retargeted"] and started["rig"]["preset"] == "ue5"
        identity = [[0.0, 0.0, 0.0, 1.0]] * len(started["joints"])
        ws.send(json.dumps({"type": "frame", "seq": 0, "root": [0.0, 95.0, 0.0], "rotations": identity}))
        check(ws.recv(timeout=30))
    with connect(url) as ws:  # binary replies: the documented layout and size
        ws.send(json.dumps({"type": "start", "model": "lti", "style": "elderly", "encoding": "binary"}))
        started = check(ws.recv(timeout=30))
        joints = started["layout"]["rotations"][0]
        ws.send(struct.pack("<IHH", 5, 1, 0) + np.concatenate([root[0], rot[0].ravel()]).astype("<f4").tobytes())
        reply = ws.recv(timeout=30)
        assert isinstance(reply, bytes) and len(reply) == 8 + 4 * (3 + 4 * joints)
        assert len(reply) == started["layout"]["binary_frame_bytes"]
        assert struct.unpack_from("<IHH", reply) == (5, 1, 0)
    with connect(url) as ws:  # a crowd (v1.1): open, a refused character, a tick, join, style, reset, leave
        chars = [{"id": 1, "model": "lti", "style": "elderly"}, {"id": 2, "model": "lti", "style": "nope"}]
        ws.send(json.dumps({"type": "crowd", "fps": 30, "characters": chars}))
        opened = check(ws.recv(timeout=30))
        assert [c["id"] for c in opened["characters"]] == [1] and opened["errors"][0]["id"] == 2
        floats = opened["rigs"][0]["frame_floats"]
        tick = np.concatenate([root[0], rot[0].ravel()]).astype("<f4")
        ws.send(struct.pack("<IHHI", 3, 2, 1, 0) + struct.pack("<I", 1) + tick.tobytes())
        reply = ws.recv(timeout=30)  # the documented layout: 12-byte header, ids, the frames
        assert isinstance(reply, bytes) and len(reply) == 12 + 4 + 4 * floats
        assert struct.unpack_from("<IHHI", reply) == (3, 2, 1, 0)
        ws.send(json.dumps({"type": "join", "characters": [{"id": 5, "model": "erd", "style": "elderly"}]}))
        assert check(ws.recv(timeout=30))["characters"][0]["id"] == 5
        ws.send(json.dumps({"type": "style", "characters": [1], "style": "exhausted"}))
        check(ws.recv(timeout=30))
        ws.send(json.dumps({"type": "reset", "characters": [5]}))
        check(ws.recv(timeout=30))
        ws.send(json.dumps({"type": "leave", "characters": [5, 9]}))
        assert check(ws.recv(timeout=30))["characters"] == [5]
        tick[4] = np.nan  # a refused frame: an error naming its character
        ws.send(struct.pack("<IHHI", 4, 2, 1, 0) + struct.pack("<I", 1) + tick.tobytes())
        assert check(ws.recv(timeout=30))["character"] == 1
        reply = ws.recv(timeout=30)  # still one reply, without the refused character
        assert isinstance(reply, bytes) and len(reply) == 12 and struct.unpack_from("<IHHI", reply) == (4, 2, 0, 0)
        ws.send(json.dumps({"type": "end"}))
        ended = check(ws.recv(timeout=30))  # last_seq: the last tick answered
        assert ended == {"type": "ended", "session_id": opened["crowd_id"], "last_seq": 4}
    assert set(seen) == set(SERVER_SCHEMAS), f"messages seen: {seen}"
