"""The README's curl examples work: every file they send exists and gets a 2xx, in the README's order."""

from __future__ import annotations

import json
import re
from pathlib import Path

from fastapi.testclient import TestClient

ROOT = Path(__file__).resolve().parent.parent
README = (ROOT / "README.md").read_text(encoding="utf-8")


def test_every_file_the_readme_sends_exists() -> None:
    paths = re.findall(r"@(tests/resources/\S+)", README)
    assert len(paths) >= 5
    for path in paths:
        assert (ROOT / path).is_file(), path


def _body(path: str) -> dict:
    return json.loads((ROOT / path).read_text(encoding="utf-8"))


def test_the_readme_walkthrough(client: TestClient) -> None:
    assert client.post("/v1/ground", json=_body("tests/resources/requests/ground.json")).status_code == 200
    small = client.post("/v1/ground", json=_body("tests/resources/requests/ground_small.json")).json()
    assert small["hypotheses"][0]["anchor_ids"] == ["t1"]  # "in the kitchen" picks the kitchen table
    assert len(small["query_log_density"]) == 1
    normalize = client.post(
        "/v1/scene-graphs/normalize",
        json=_body("tests/resources/scene_graphs/region_grouped_paper_example.json"),
    )
    assert normalize.status_code == 200
    for path in ("/v1/models", "/healthz", "/readyz", "/metrics"):
        assert client.get(path).status_code == 200

    sid = client.post("/v1/sessions", json=_body("tests/resources/requests/session.json")).json()["id"]
    assert client.get("/v1/sessions", params={"robot_id": "robot-7"}).status_code == 200
    assert client.get(f"/v1/sessions/{sid}").status_code == 200
    utterance = {"utterance": "I left my backpack on the table in the kitchen"}
    assert client.post(f"/v1/sessions/{sid}/utterances", json=utterance).status_code == 200
    observed = client.post(
        f"/v1/sessions/{sid}/observations", json=_body("tests/resources/requests/observations.json")
    )
    assert observed.status_code == 200
    belief = client.get(f"/v1/sessions/{sid}/belief")
    assert belief.headers["etag"] == '"v2"'  # the README's If-None-Match example
    assert client.get(f"/v1/sessions/{sid}/belief", headers={"If-None-Match": '"v2"'}).status_code == 304
    grid = client.get(f"/v1/sessions/{sid}/belief", params={"format": "grid", "layers": "true"})
    assert grid.headers["content-type"] == "application/msgpack"
    assert (
        client.put(
            f"/v1/sessions/{sid}/scene-graph", json=_body("tests/resources/scenes/two_rooms.json")
        ).status_code
        == 200
    )
    assert client.delete(f"/v1/sessions/{sid}").status_code == 204
