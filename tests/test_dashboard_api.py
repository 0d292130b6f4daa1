"""What the dashboard reads besides the summary and the push stream: the top-down view of the belief, the
session's scene graph and its utterances with their readings; and the page itself, served with its assets.
(The page in a real browser: tests/test_dashboard_browser.py.)"""

from __future__ import annotations

import asyncio
import base64
import json
import uuid
from collections.abc import Iterator
from html.parser import HTMLParser
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest
from fastapi.testclient import TestClient

from app.api.app import create_app
from app.api.auth import digest, new_key
from app.api.routes.dashboard import DASHBOARD_DIR
from app.api.routes.events import BeliefEvent
from app.belief import fusion
from app.belief.grid import VoxelGrid
from app.belief.summary import column_mass
from tests.conftest import model_free_settings

SCENE = json.loads(
    (Path(__file__).resolve().parent / "resources" / "scenes" / "two_rooms.json").read_text(encoding="utf-8")
)
VIEWER, ROBOT, OTHER = new_key(), new_key(), new_key()
KEYS = [
    {"name": "viewer", "role": "viewer", "sha256": digest(VIEWER)},
    {"name": "robot", "role": "robot", "sha256": digest(ROBOT), "robot_ids": ["r1"]},
    {"name": "other", "role": "robot", "sha256": digest(OTHER), "robot_ids": ["r2"]},
]


def auth(key: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {key}"}


@pytest.fixture
def keyed() -> Iterator[TestClient]:
    with TestClient(create_app(model_free_settings(api_keys=json.dumps(KEYS)))) as client:
        yield client


def create(client: TestClient, **fields: Any) -> str:
    body = {"robot_id": "r1", "scene_graph": SCENE, "target_label": "backpack", **fields}
    answer = client.post("/v1/sessions", json=body, headers=auth(ROBOT))
    assert answer.status_code == 201, answer.text
    return str(answer.json()["id"])


def say(client: TestClient, session_id: str, utterance: str) -> dict[str, Any]:
    answer = client.post(
        f"/v1/sessions/{session_id}/utterances", json={"utterance": utterance}, headers=auth(ROBOT)
    )
    assert answer.status_code == 200, answer.text
    body: dict[str, Any] = answer.json()
    return body


def top_down(answer: dict[str, Any]) -> np.ndarray:
    nx, ny = answer["shape"]
    return np.frombuffer(base64.b64decode(answer["mass"]), dtype="<f4").reshape(nx, ny)


def test_column_mass_is_the_posterior_summed_over_z_in_chunks_and_at_extremes() -> None:
    rng = np.random.default_rng(3)
    grid = VoxelGrid(origin=(-1.0, 2.0, 0.0), shape=(37, 23, 150), voxel_size=0.1)  # several chunks
    lang = rng.normal(0.0, 3.0, grid.n_voxels).astype(np.float32)
    vis = rng.normal(0.0, 3.0, grid.n_voxels).astype(np.float32)
    lang[5] = 500.0  # far above every other voxel: the rest underflows, floored as in the summary
    expected = fusion.posterior(lang, vis).reshape(grid.shape).sum(axis=2)
    got = column_mass(grid, lang, vis)
    assert got.shape == (37, 23) and got.dtype == np.float32
    assert np.allclose(got, expected, rtol=1e-5, atol=1e-9)
    assert np.isclose(float(got.sum(dtype=np.float64)), 1.0)
    flat = column_mass(grid, np.zeros_like(lang), np.zeros_like(vis))
    assert np.allclose(flat, 1.0 / (37 * 23))


def test_the_top_down_view_is_the_belief_seen_from_above_with_its_version(keyed: TestClient) -> None:
    sid = create(keyed)
    say(keyed, sid, "I left my backpack on the table in the kitchen")
    answer = keyed.get(f"/v1/sessions/{sid}/belief/topdown", headers=auth(VIEWER))
    assert answer.status_code == 200 and answer.headers["etag"] == '"v1"'
    view = answer.json()
    grid = keyed.get(f"/v1/sessions/{sid}", headers=auth(VIEWER)).json()["grid"]
    assert view["version"] == 1 and view["shape"] == grid["shape"][:2]
    assert view["min_corner"] == grid["min_corner"][:2] and view["voxel_size"] == grid["voxel_size"]
    mass = top_down(view)
    assert np.isclose(float(mass.sum(dtype=np.float64)), 1.0) and view["max_mass"] == pytest.approx(
        mass.max()
    )
    # The heaviest column is under the summary's MAP voxel.
    summary = keyed.get(f"/v1/sessions/{sid}/belief", headers=auth(VIEWER)).json()["summary"]
    x, y, _ = summary["map_voxel"]["center"]
    i, j = np.unravel_index(int(mass.argmax()), mass.shape)
    x0, y0 = view["min_corner"]
    s = view["voxel_size"]
    assert abs(x0 + (i + 0.5) * s - x) < 0.2 and abs(y0 + (j + 0.5) * s - y) < 0.2
    unchanged = keyed.get(
        f"/v1/sessions/{sid}/belief/topdown", headers={**auth(VIEWER), "If-None-Match": '"v1"'}
    )
    assert unchanged.status_code == 304 and unchanged.headers["etag"] == '"v1"'
    say(keyed, sid, "my backpack is on the sofa")
    newer = keyed.get(f"/v1/sessions/{sid}/belief/topdown", headers={**auth(VIEWER), "If-None-Match": '"v1"'})
    assert newer.status_code == 200 and newer.json()["version"] == 2
    assert not np.array_equal(top_down(newer.json()), mass)


def test_the_dashboard_reads_need_read_access(keyed: TestClient) -> None:
    sid = create(keyed)
    for path in ("belief/topdown", "scene-graph", "utterances"):
        assert keyed.get(f"/v1/sessions/{sid}/{path}").status_code == 401
        assert keyed.get(f"/v1/sessions/{sid}/{path}", headers=auth(OTHER)).status_code == 403
        assert keyed.get(f"/v1/sessions/{sid}/{path}", headers=auth(ROBOT)).status_code == 200
        missing = keyed.get(f"/v1/sessions/{uuid.uuid4().hex}/{path}", headers=auth(VIEWER))
        assert missing.status_code == 404 and missing.json()["code"] == "not_found"


def test_the_scene_graph_is_the_latest_replacement(keyed: TestClient) -> None:
    sid = create(keyed)
    first = keyed.get(f"/v1/sessions/{sid}/scene-graph", headers=auth(VIEWER)).json()
    assert [o["id"] for o in first["objects"]] == [o["id"] for o in SCENE["objects"]]
    smaller = {**SCENE, "objects": SCENE["objects"][:2]}
    assert keyed.put(f"/v1/sessions/{sid}/scene-graph", json=smaller, headers=auth(ROBOT)).status_code == 200
    now = keyed.get(f"/v1/sessions/{sid}/scene-graph", headers=auth(VIEWER)).json()
    assert [o["id"] for o in now["objects"]] == [o["id"] for o in SCENE["objects"][:2]]


def test_utterances_come_with_their_readings_in_the_history_and_on_the_stream(keyed: TestClient) -> None:
    sid = create(keyed)
    said = say(keyed, sid, "I left my backpack on the table in the kitchen")
    refused = say(keyed, sid, "the mug is on the sofa")
    assert said["fused"] and not refused["fused"]
    history = keyed.get(f"/v1/sessions/{sid}/utterances", headers=auth(VIEWER)).json()
    assert history["session_id"] == sid and history["complete"]
    first, second = history["utterances"]
    assert first["utterance"] == "I left my backpack on the table in the kitchen" and first["fused"]
    assert first["version"] == 1 and second["version"] == 1 and not second["fused"] and second["reason"]
    readings = said["grounding"]["hypotheses"]
    assert [(h["text"], h["weight"], h["anchor_ids"]) for h in first["hypotheses"]] == [
        (h["text"], h["weight"], h["anchor_ids"]) for h in readings
    ]
    assert sum(h["weight"] for h in first["hypotheses"]) == pytest.approx(1.0)
    # The records are the push stream's events (the store's history of them), with their ids.
    store = keyed.app.state.services.store  # type: ignore[attr-defined]
    events = [e for e in asyncio.run(store.events.retained(sid)) if e.kind == "utterance"]
    assert [e.stream_id for e in events] == [first["event_id"], second["event_id"]]
    for event in events:
        BeliefEvent.model_validate_json(event.data)  # the documented event, readings included


def test_the_utterance_history_says_when_it_no_longer_reaches_back() -> None:
    with TestClient(create_app(model_free_settings(events_history=3))) as client:
        sid = client.post(
            "/v1/sessions", json={"robot_id": "r1", "scene_graph": SCENE, "target_label": "backpack"}
        )
        session_id = sid.json()["id"]
        for utterance in (
            "my backpack is on the table",
            "my backpack is on the sofa",
            "it is in the kitchen",
        ):
            client.post(f"/v1/sessions/{session_id}/utterances", json={"utterance": utterance})
        history = client.get(f"/v1/sessions/{session_id}/utterances").json()
        assert not history["complete"]
        assert [u["utterance"] for u in history["utterances"]] == [
            "my backpack is on the table",
            "my backpack is on the sofa",
            "it is in the kitchen",
        ]


@pytest.mark.redis
def test_the_utterance_history_on_redis(redis_url: str) -> None:
    from app.stores.redis_store import RedisSessionStore

    store = RedisSessionStore(redis_url, prefix=f"test-{uuid.uuid4().hex[:8]}")
    with TestClient(create_app(model_free_settings(), store=store)) as client:
        created = client.post(
            "/v1/sessions", json={"robot_id": "r1", "scene_graph": SCENE, "target_label": "backpack"}
        )
        sid = created.json()["id"]
        client.post(f"/v1/sessions/{sid}/utterances", json={"utterance": "my backpack is on the sofa"})
        history = client.get(f"/v1/sessions/{sid}/utterances").json()
        assert history["complete"] and [u["utterance"] for u in history["utterances"]] == [
            "my backpack is on the sofa"
        ]
        assert history["utterances"][0]["hypotheses"]
        mass = top_down(client.get(f"/v1/sessions/{sid}/belief/topdown").json())
        assert np.isclose(float(mass.sum(dtype=np.float64)), 1.0)
    store.close()


class _Assets(HTMLParser):
    def __init__(self) -> None:
        super().__init__()
        self.urls: list[str] = []

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        for name, value in attrs:
            if name in ("src", "href") and value is not None:
                self.urls.append(value)


def test_the_page_and_its_assets_are_served_without_a_key_and_load_nothing_else(keyed: TestClient) -> None:
    page = keyed.get("/dashboard")
    assert page.status_code == 200 and page.headers["content-type"].startswith("text/html")
    policy = page.headers["content-security-policy"]
    assert "default-src 'none'" in policy and "connect-src 'self'" in policy and "script-src 'self'" in policy
    parser = _Assets()
    parser.feed(page.text)
    assert len(parser.urls) == 3, parser.urls  # the icon, the stylesheet, the script
    for url in parser.urls:
        assert not url.startswith(("/", "http:", "https:")), url  # relative: behind a proxy's prefix too
        assert keyed.get(f"/{url}").status_code == 200, url
    for name, kind in (("dashboard.js", "text/javascript"), ("dashboard.css", "text/css")):
        asset = keyed.get(f"/dashboard/{name}")
        assert asset.headers["content-type"].startswith(kind)
        assert asset.content == (DASHBOARD_DIR / name).read_bytes()
        assert "http:" not in asset.text and "https:" not in asset.text  # nothing from the web
    assert keyed.get("/dashboard/index.html").status_code == 404
    assert keyed.get("/dashboard/../app.py").status_code == 404
    assert keyed.get("/v1/sessions").status_code == 401  # the API still wants the key


def test_the_page_is_not_in_the_api_contract(keyed: TestClient) -> None:
    paths = keyed.get("/openapi.json").json()["paths"]
    assert not [path for path in paths if path.startswith("/dashboard")]


def test_the_client_reads_the_top_down_view_scene_graph_and_utterances() -> None:
    from app.client import VLMapClient
    from tests.test_events import served

    with (
        served(model_free_settings(api_keys=json.dumps(KEYS))) as server,
        VLMapClient(server.url, api_key=ROBOT) as robot,
        VLMapClient(server.url, api_key=VIEWER) as viewer,
    ):
        session_id = robot.create_session("r1", SCENE, target_label="backpack")["id"]
        robot.send_utterance(session_id, "I left my backpack on the table")
        raw = httpx.get(f"{server.url}/v1/sessions/{session_id}/belief/topdown", headers=auth(VIEWER)).json()
        view, etag = viewer.get_belief_topdown(session_id)
        assert view is not None and etag == f'"v{raw["version"]}"' and view.version == raw["version"]
        assert view.mass.shape == tuple(raw["shape"]) and np.array_equal(view.mass, top_down(raw))
        assert view.min_corner == tuple(raw["min_corner"]) and view.voxel_size == raw["voxel_size"]
        assert viewer.get_belief_topdown(session_id, etag) == (None, etag)  # unchanged: 304
        graph = viewer.get_scene_graph(session_id)
        assert sorted(o["id"] for o in graph["objects"]) == sorted(str(o["id"]) for o in SCENE["objects"])
        history = viewer.list_utterances(session_id)
        assert [u["utterance"] for u in history["utterances"]] == ["I left my backpack on the table"]
