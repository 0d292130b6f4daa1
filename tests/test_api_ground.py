"""POST /v1/ground end to end, in process."""

from __future__ import annotations

import copy
import json
from collections.abc import Iterator
from dataclasses import replace
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient

from app.api.app import create_app
from app.api.bootstrap import Sensors
from app.api.routes.ground import to_response
from app.grounding.geometric import GeometricGrounder
from app.grounding.hypotheses import MIN_BACKGROUND_WEIGHT, Hypothesis
from app.grounding.lexical import LexicalProposer
from app.grounding.mixture import Gaussian, GaussianMixture, UniformBox, map_box
from app.grounding.relations import Relation
from app.grounding.sensor import LanguageSensor, merged_tail
from app.scene_graph.model import SceneGraph
from app.settings import Settings
from tests.conftest import model_free_settings


class BoxedGrounder:
    """The geometric grounder's Gaussian per hypothesis with a wider tail and a uniform box around it: a
    density of two Gaussians and a box (weights 0.6, 0.3, 0.1), as a grounder serving boxes answers."""

    name = "boxed"
    version = "test"
    weights = (0.6, 0.3, 0.1)

    def __init__(self) -> None:
        self.inner = GeometricGrounder()

    def ground(
        self, scene_graph: SceneGraph, utterance: str, hypotheses: list[Hypothesis]
    ) -> list[GaussianMixture]:
        out = []
        for core in self.inner.ground(scene_graph, utterance, hypotheses):
            mean, cov = core.means[0], core.covariances[0]
            out.append(
                GaussianMixture.from_components(
                    self.weights[:2],
                    [Gaussian(mean, cov), Gaussian(mean, 4.0 * cov)],
                    boxes=[UniformBox.around(mean - 0.3, mean + 0.3)],
                    box_weights=self.weights[2:],
                )
            )
        return out

    def describe(self) -> dict[str, Any]:
        return {"name": self.name, "version": self.version, "config": {}, "checksum": None}


def boxed_sensors() -> Sensors:
    """The lexical proposer and `BoxedGrounder`, the service's only grounder."""
    return Sensors(
        grounders={"boxed": BoxedGrounder()}, proposers={"builtin": LexicalProposer()}, default="boxed"
    )


@pytest.fixture
def boxed_client() -> Iterator[TestClient]:
    """A service whose mixtures hold uniform boxes beside their Gaussians."""
    with TestClient(create_app(model_free_settings(), sensors=boxed_sensors())) as test_client:
        yield test_client


def served_mixture(mixture: dict[str, Any]) -> GaussianMixture:
    """The density a response's `mixture` describes: its Gaussians and its uniform boxes."""
    return GaussianMixture.from_components(
        [c["weight"] for c in mixture["components"]],
        [Gaussian(np.array(c["mean"]), np.array(c["covariance"])) for c in mixture["components"]],
        boxes=[UniformBox(np.array(b["low"]), np.array(b["high"])) for b in mixture["uniform"]],
        box_weights=[b["weight"] for b in mixture["uniform"]],
    )


def _ground(client: TestClient, scene_graph: Any, utterance: str, **extra: Any) -> Any:
    return client.post("/v1/ground", json={"scene_graph": scene_graph, "utterance": utterance, **extra})


def _assert_valid_mixture(mixture: dict[str, Any]) -> None:
    weights = [c["weight"] for c in mixture["components"]] + [b["weight"] for b in mixture["uniform"]]
    assert sum(weights) == pytest.approx(1.0)
    for component in mixture["components"]:
        cov = np.array(component["covariance"])
        assert cov.shape == (3, 3)
        np.testing.assert_allclose(cov, cov.T)
        assert np.linalg.eigvalsh(cov).min() > 0
    for box in mixture["uniform"]:
        assert all(hi > lo for lo, hi in zip(box["low"], box["high"], strict=True))


def test_two_tables_give_two_equally_weighted_hypotheses(client: TestClient, scene_graph_dict: dict) -> None:
    response = _ground(client, scene_graph_dict, "I left my backpack on the table")
    assert response.status_code == 200, response.text
    body = response.json()
    tables = {o["id"] for o in scene_graph_dict["objects"] if o["label"] == "table"}
    assert len(tables) == 2
    assert {h["anchor_ids"][0] for h in body["hypotheses"]} == tables
    assert [h["weight"] for h in body["hypotheses"]] == pytest.approx([0.5, 0.5])
    assert body["target"] == {"label": "backpack"}
    assert body["grounded"] is True
    assert body["parse"]["relation"] == "on"
    assert body["model"]["name"] == "geometric"
    assert set(body["timings_ms"]) == {"proposer", "grounder"}
    _assert_valid_mixture(body["mixture"])
    # Each hypothesis's component sits just above its table; the last, of no hypothesis, is the broad term's
    # wide Gaussian.
    by_id = {o["id"]: o for o in scene_graph_dict["objects"]}
    assert [c["hypothesis"] for c in body["mixture"]["components"]] == [0, 1, None]
    for c in body["mixture"]["components"][:2]:
        table = by_id[body["hypotheses"][c["hypothesis"]]["anchor_ids"][0]]
        top = table["center"][2] + table["size"][2] / 2
        assert c["mean"][2] == pytest.approx(top + 0.1)


def test_query_points_return_the_mixture_log_density(client: TestClient, scene_graph_dict: dict) -> None:
    table = next(o for o in scene_graph_dict["objects"] if o["label"] == "desk")
    on_top = [table["center"][0], table["center"][1], table["center"][2] + table["size"][2] / 2 + 0.1]
    far = [on_top[0] + 5.0, on_top[1] + 5.0, on_top[2]]
    body = _ground(client, scene_graph_dict, "the mouse is on the desk", query_points=[on_top, far]).json()
    mixture = served_mixture(body["mixture"])
    np.testing.assert_allclose(body["query_log_density"], mixture.logpdf(np.array([on_top, far])), rtol=1e-9)
    assert body["query_log_density"][0] > body["query_log_density"][1]


def test_between_pairs_two_anchors(client: TestClient, scene_graph_dict: dict) -> None:
    body = _ground(client, scene_graph_dict, "the umbrella is between the desk and the lamp").json()
    assert body["hypotheses"][0]["relation"] == "between"
    assert len(body["hypotheses"][0]["anchor_ids"]) == 2
    _assert_valid_mixture(body["mixture"])


def test_caller_hypotheses_are_grounded_as_given(client: TestClient, scene_graph_dict: dict) -> None:
    desk = next(o["id"] for o in scene_graph_dict["objects"] if o["label"] == "desk")
    options = {"hypotheses": [{"anchor_ids": [desk], "relation": "near", "weight": 3}]}
    body = _ground(client, scene_graph_dict, "my bag is somewhere there", options=options).json()
    assert [(h["anchor_ids"], h["relation"], h["weight"]) for h in body["hypotheses"]] == [
        ([desk], "near", 1.0)
    ]
    assert "proposer" not in body["timings_ms"]


def test_caller_weights_are_relative_even_near_the_float_maximum(
    client: TestClient, scene_graph_dict: dict
) -> None:
    tables = [o["id"] for o in scene_graph_dict["objects"] if o["label"] == "table"][:2]
    options = {"hypotheses": [{"anchor_ids": [t], "relation": "on", "weight": 1e308} for t in tables]}
    response = _ground(client, scene_graph_dict, "my bag is on the table", options=options)
    assert response.status_code == 200, response.text
    assert [h["weight"] for h in response.json()["hypotheses"]] == pytest.approx([0.5, 0.5])


def test_the_merged_tail_names_its_heaviest_relation_ties_going_to_the_first(scene_graph_dict: dict) -> None:
    scene_graph = SceneGraph.model_validate(scene_graph_dict)
    anchors = [o.id for o in scene_graph.objects[:4]]
    for first, second in (
        (Relation.ON, Relation.NEAR),
        (Relation.NEAR, Relation.ON),
        (Relation.IN, Relation.ABOVE),
    ):
        group = [
            Hypothesis((a,), relation, 0.25) for a, relation in zip(anchors, (first, second) * 2, strict=True)
        ]
        ((merged, _),) = merged_tail(scene_graph, group, map_box(scene_graph))
        assert merged.relation is first


@pytest.mark.parametrize(
    ("hypothesis", "fragment"),
    [
        ({"anchor_ids": ["no-such-id"], "relation": "on"}, "unknown object id"),
        ({"anchor_ids": ["1"], "relation": "between"}, "takes 2 anchor id"),
    ],
)
def test_bad_caller_hypotheses_are_422_naming_the_field(
    client: TestClient, scene_graph_dict: dict, hypothesis: dict, fragment: str
) -> None:
    response = _ground(client, scene_graph_dict, "x on y", options={"hypotheses": [hypothesis]})
    assert response.status_code == 422
    assert response.json()["field"] == "options.hypotheses.0.anchor_ids"
    assert fragment in response.json()["message"]


def test_unmatched_anchor_falls_back_to_a_broad_prior(client: TestClient, scene_graph_dict: dict) -> None:
    body = _ground(client, scene_graph_dict, "my keys are on the piano").json()
    assert body["grounded"] is False
    assert "piano" in body["reason"]
    assert body["hypotheses"] == []
    _assert_valid_mixture(body["mixture"])
    # The broad prior: uniform over the map's box (nine tenths of the mass and the floor), and a wide
    # Gaussian about it (a tenth, of no hypothesis) for the places just outside.
    (wide,) = body["mixture"]["components"]
    assert wide["hypothesis"] is None and wide["weight"] == pytest.approx(0.1 * (1 - MIN_BACKGROUND_WEIGHT))
    box = map_box(SceneGraph.model_validate(scene_graph_dict))
    for term in body["mixture"]["uniform"]:
        assert term["low"] == pytest.approx(box.low.tolist()) and term["high"] == pytest.approx(
            box.high.tolist()
        )
    assert sum(t["weight"] for t in body["mixture"]["uniform"]) == pytest.approx(1.0 - wide["weight"])


def _mutated(scene_graph: dict, path: tuple[Any, ...], value: Any) -> dict:
    out = copy.deepcopy(scene_graph)
    node = out
    for key in path[:-1]:
        node = node[key]
    node[path[-1]] = value
    return out


@pytest.mark.parametrize(
    ("path", "value", "field", "fragment"),
    [
        (("objects", 3, "size"), [0.5, 0.0, 0.2], "scene_graph.objects.3.size", "strictly positive"),
        (("objects", 4, "size"), [0.5, -1.0, 0.2], "scene_graph.objects.4.size", "strictly positive"),
        (("objects", 5, "region_id"), "nowhere", "scene_graph", "objects[5].region_id: unknown region id"),
        (("objects", 6, "id"), "0", "scene_graph", "duplicate object ids"),
        (("objects", 2, "center"), [1.0, 2.0], "scene_graph.objects.2.center", "at least 3"),
        (("objects", 2, "label"), "", "scene_graph.objects.2.label", "at least 1"),
    ],
)
def test_bad_scene_graphs_are_422_naming_the_field(
    client: TestClient, scene_graph_dict: dict, path: tuple, value: Any, field: str, fragment: str
) -> None:
    response = _ground(client, _mutated(scene_graph_dict, path, value), "the bag is on the table")
    assert response.status_code == 422, response.text
    body = response.json()
    assert body["code"] == "invalid_input"
    assert body["field"] == field
    assert fragment in body["message"]


@pytest.mark.parametrize("token", ["NaN", "Infinity", "-Infinity"])
def test_non_finite_numbers_are_422(client: TestClient, scene_graph_dict: dict, token: str) -> None:
    text = json.dumps({"scene_graph": scene_graph_dict, "utterance": "the bag is on the table"})
    first_center = json.dumps(scene_graph_dict["objects"][0]["center"])
    text = text.replace(first_center, f"[{token}, 1.0, 1.0]", 1)
    response = client.post("/v1/ground", content=text, headers={"content-type": "application/json"})
    assert response.status_code == 422, response.text
    assert response.json()["field"] == "scene_graph.objects.0.center"
    assert "finite" in response.json()["message"]


def test_object_cap_is_enforced(scene_graph_dict: dict) -> None:
    settings = Settings(_env_file=None, max_objects=10, log_json=False, data_dir=None)  # type: ignore[call-arg]
    with TestClient(create_app(settings)) as small:
        response = _ground(small, scene_graph_dict, "the bag is on the table")
    assert response.status_code == 422
    assert response.json()["code"] == "limit_exceeded"
    assert "60 objects exceed the limit of 10" in response.json()["message"]


def test_request_id_is_echoed_or_created(client: TestClient) -> None:
    assert client.get("/healthz", headers={"X-Request-ID": "abc-123"}).headers["x-request-id"] == "abc-123"
    generated = client.get("/healthz").headers["x-request-id"]
    assert len(generated) == 32


def test_errors_carry_the_request_id(client: TestClient) -> None:
    response = client.post("/v1/ground", json={"utterance": "x"}, headers={"X-Request-ID": "req-9"})
    assert response.status_code == 422
    assert response.json()["request_id"] == "req-9"
    assert response.json()["field"] == "scene_graph"


def test_a_request_may_pick_another_loaded_grounder(client: TestClient, scene_graph_dict: dict) -> None:
    options = {"grounder": "fixed"}
    body = _ground(client, scene_graph_dict, "the bag is on the desk", options=options).json()
    assert body["model"]["name"] == "fixed"
    np.testing.assert_allclose(body["mixture"]["components"][0]["covariance"], np.eye(3) * 0.01)


def test_an_unloaded_grounder_is_422(client: TestClient, scene_graph_dict: dict) -> None:
    response = _ground(client, scene_graph_dict, "the bag is on the desk", options={"grounder": "lsm"})
    assert response.status_code == 422
    assert response.json()["field"] == "options.grounder"


def test_curl_d_without_a_content_type_header_works(client: TestClient, scene_graph_dict: dict) -> None:
    """`curl -d @file` sends a form content type; the body is read as JSON."""
    body = json.dumps({"scene_graph": scene_graph_dict, "utterance": "the bag is on the desk"})
    headers = {"content-type": "application/x-www-form-urlencoded"}
    response = client.post("/v1/ground", content=body, headers=headers)
    assert response.status_code == 200, response.text
    garbage = client.post("/v1/ground", content="utterance=hello", headers=headers)
    assert garbage.status_code == 422


def test_uniform_boxes_are_served_beside_the_gaussians_of_each_hypothesis(
    boxed_client: TestClient, scene_graph_dict: dict
) -> None:
    table = next(o for o in scene_graph_dict["objects"] if o["label"] == "table")
    on_top = [table["center"][0], table["center"][1], table["center"][2] + table["size"][2] / 2 + 0.1]
    points = [on_top, [on_top[0] + 0.25, *on_top[1:]], [on_top[0] + 5.0, *on_top[1:]]]
    body = _ground(
        boxed_client, scene_graph_dict, "I left my backpack on the table", query_points=points
    ).json()
    hypotheses, mixture = body["hypotheses"], body["mixture"]
    # Each hypothesis's box, then the broad term's (the map's box for beta_min, the broad density's).
    assert len(hypotheses) == 2 and len(mixture["uniform"]) == 4
    _assert_valid_mixture(mixture)
    keep = 1.0 - MIN_BACKGROUND_WEIGHT  # the lexical proposer leaves the broad term at its floor
    # Two Gaussians per hypothesis, in hypothesis order, each pointing at its hypothesis; then the wide one.
    assert [c["hypothesis"] for c in mixture["components"]] == [0, 0, 1, 1, None]
    by_id = {o["id"]: o for o in scene_graph_dict["objects"]}
    for component in mixture["components"][:4]:
        h = hypotheses[component["hypothesis"]]
        table = by_id[h["anchor_ids"][0]]
        assert component["mean"][:2] == pytest.approx(table["center"][:2])
    for h, pair in zip(hypotheses, [mixture["components"][:2], mixture["components"][2:4]], strict=True):
        assert [c["weight"] for c in pair] == pytest.approx(
            [0.6 * keep * h["weight"], 0.3 * keep * h["weight"]]
        )
    for h, box in zip(hypotheses, mixture["uniform"][:2], strict=True):
        assert box["weight"] == pytest.approx(0.1 * keep * h["weight"])
        table = by_id[h["anchor_ids"][0]]
        centre = [(lo + hi) / 2 for lo, hi in zip(box["low"], box["high"], strict=True)]
        assert centre[:2] == pytest.approx(table["center"][:2])
        assert [hi - lo for lo, hi in zip(box["low"], box["high"], strict=True)] == pytest.approx([0.6] * 3)
    # The served terms are the whole density: they give the log-density the service computed.
    expected = served_mixture(mixture).logpdf(np.array(points))
    np.testing.assert_allclose(body["query_log_density"], expected, rtol=1e-9)


def test_a_background_box_appended_to_the_mixture_belongs_to_no_hypothesis(scene_graph_dict: dict) -> None:
    scene_graph = SceneGraph.model_validate(scene_graph_dict)
    sensor = LanguageSensor(LexicalProposer(), BoxedGrounder())
    result = sensor.ground(scene_graph, "I left my backpack on the table")
    low, high = scene_graph.bounds()
    background = UniformBox(np.asarray(low), np.asarray(high))
    body = to_response(replace(result, mixture=result.mixture.with_background(0.2, background)), sensor, None)
    mixture = body.mixture.model_dump()
    _assert_valid_mixture(mixture)
    assert [c["hypothesis"] for c in mixture["components"]] == [0, 0, 1, 1, None]
    weights = [b["weight"] for b in mixture["uniform"]]
    assert weights[:2] == pytest.approx([0.8 * 0.049, 0.8 * 0.049]) and weights[-1] == pytest.approx(0.2)
    assert mixture["uniform"][-1]["low"] == background.low.tolist()
    assert mixture["uniform"][-1]["high"] == background.high.tolist()
