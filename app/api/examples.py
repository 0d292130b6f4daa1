"""Request examples of the OpenAPI document, which Swagger UI at `/docs` offers under "Try it out".

They are the requests of the README's "The API by example" (the files under `tests/resources/requests/`
and the two-room map `tests/resources/scenes/two_rooms.json`, written out here) and a few variants: for
each operation that takes a JSON body, named `examples` of that body (`BODY_EXAMPLES`, by operation id);
for parameters, named `examples` by parameter name (`PARAMETER_EXAMPLES`, the same for every operation that
has the parameter, unless `OPERATION_PARAMETER_EXAMPLES` gives that operation its own). A session id in the
examples is made up: create a session first and paste its id.
"""

from __future__ import annotations

import copy
from typing import Any

#: The README's two-room map (tests/resources/scenes/two_rooms.json).
TWO_ROOMS: dict[str, Any] = {
    "frame_id": "map",
    "regions": [
        {"id": "kitchen", "name": "kitchen", "center": [2, 0, 1.2], "size": [4, 4, 2.4]},
        {"id": "living", "name": "living room", "center": [-2, 0, 1.2], "size": [4, 4, 2.4]},
    ],
    "objects": [
        {
            "id": "t1",
            "label": "table",
            "center": [1.5, 0.5, 0.375],
            "size": [1.2, 0.8, 0.75],
            "region_id": "kitchen",
        },
        {
            "id": "t2",
            "label": "table",
            "center": [-2.0, 1.0, 0.225],
            "size": [0.9, 0.6, 0.45],
            "region_id": "living",
            "attributes": {"color": "white"},
        },
        {
            "id": "c1",
            "label": "kitchen counter",
            "center": [3.6, -1.0, 0.45],
            "size": [0.6, 2.0, 0.9],
            "region_id": "kitchen",
        },
        {
            "id": "s1",
            "label": "sofa",
            "center": [-2.5, -1.2, 0.4],
            "size": [2.0, 0.9, 0.8],
            "region_id": "living",
        },
    ],
}

#: The reference paper's region-grouped serialization
#: (tests/resources/scene_graphs/region_grouped_paper_example.json, the office).
REGION_GROUPED: dict[str, Any] = {
    "Office": {
        "objects": {
            "0": {
                "semantics": "desk",
                "raw_label": "wooden desk",
                "center": [0.0, -1.0, 0.4],
                "volume": 2.5,
                "object_id": "0",
            },
            "1": {
                "semantics": "monitor",
                "raw_label": "computer monitor",
                "center": [0.1, -1.0, 0.9],
                "volume": 0.04,
                "object_id": "1",
            },
            "3": {
                "semantics": "chair",
                "raw_label": "office chair",
                "center": [0.8, -0.6, 0.5],
                "volume": 0.3,
                "object_id": "3",
            },
        },
        "region_id": 0,
    }
}


def _example(summary: str, value: Any, description: str | None = None) -> dict[str, Any]:
    example: dict[str, Any] = {"summary": summary, "value": value}
    if description:
        example["description"] = description
    return example


#: Named examples of each operation's JSON request body, by operation id.
BODY_EXAMPLES: dict[str, dict[str, dict[str, Any]]] = {
    "ground": {
        "two_rooms": _example(
            "A region mention, and the log-density at a query point",
            {
                "scene_graph": TWO_ROOMS,
                "utterance": "I left my backpack on the table in the kitchen",
                "query_points": [[1.5, 0.5, 0.85]],
            },
            "tests/resources/requests/ground_small.json",
        ),
        "given_hypotheses": _example(
            "Ground given hypotheses with the geometric grounder (no proposer)",
            {
                "scene_graph": TWO_ROOMS,
                "utterance": "the backpack is on the table",
                "options": {
                    "grounder": "geometric",
                    "hypotheses": [
                        {"anchor_ids": ["t1"], "relation": "on", "weight": 0.7},
                        {"anchor_ids": ["t2"], "relation": "on", "weight": 0.3},
                    ],
                },
            },
        ),
    },
    "normalize_scene_graph": {
        "region_grouped": _example("The reference paper's region-grouped JSON", REGION_GROUPED),
        "native": _example("A native scene graph (returned as it is, checked)", TWO_ROOMS),
    },
    "create_session": {
        "two_rooms": _example(
            "A belief over the two-room map, looking for a backpack",
            {
                "robot_id": "robot-7",
                "scene_graph": TWO_ROOMS,
                "target_label": "backpack",
                "sensor_model": {"tp": 0.9, "fp": 0.05},
            },
            "tests/resources/requests/session.json",
        ),
        "label_map": _example(
            "With a label map (observations then send integer ids) and the grid spelled out",
            {
                "robot_id": "robot-7",
                "scene_graph": TWO_ROOMS,
                "target_label": "backpack",
                "grid": {"voxel_size": 0.1, "margin": 0.5},
                "label_map": {"0": "floor", "1": "backpack", "2": "table"},
            },
        ),
    },
    "replace_scene_graph": {
        "two_rooms": _example("The map Hydra keeps building (any accepted JSON format)", TWO_ROOMS),
    },
    "add_utterance": {
        "place": _example(
            "Where the target was left", {"utterance": "I left my backpack on the table in the kitchen"}
        ),
        "grounder": _example(
            "With the geometric grounder for this utterance",
            {"utterance": "my backpack is on the sofa", "options": {"grounder": "geometric"}},
        ),
    },
    "add_observations": {
        "points": _example(
            "Points and class names",
            {
                "stamp": 12.5,
                "points": [[1.5, 0.5, 0.85], [1.6, 0.5, 0.85], [-2.0, 1.0, 0.55], [0.0, 0.0, 0.05]],
                "labels": ["backpack", "backpack", "table", "floor"],
            },
            "tests/resources/requests/observations.json",
        ),
        "voxels": _example(
            "Voxel indices and label-map ids",
            {"stamp": 13.0, "voxels": [[60, 30, 13], [61, 30, 13]], "labels": [1, 1]},
            "Ids of the session's label_map; [60, 30, 13] is the voxel above table t1 on a 0.1 m grid.",
        ),
        "detector": _example(
            "A detector's probability that each point holds the target",
            {"stamp": 13.5, "points": [[1.5, 0.5, 0.85], [-2.0, 1.0, 0.55]], "p_target": [0.8, 0.1]},
        ),
    },
}

_SESSION_ID = "5f0c3d2a9b8e4f7a8c1d2e3f4a5b6c7d"

#: Named examples of parameters, by parameter name (headers compared without case).
PARAMETER_EXAMPLES: dict[str, dict[str, dict[str, Any]]] = {
    "session_id": {"session": _example("A session id (from POST /v1/sessions)", _SESSION_ID)},
    "robot_id": {"robot": _example("One robot's sessions", "robot-7")},
    "idempotency-key": {"key": _example("Any 1-255 printable ASCII characters", "robot-7-batch-000123")},
    "if-none-match": {"version": _example("The ETag of a belief already read", '"v2"')},
    "top_k": {"ten": _example("Ten top voxels", 10)},
    "layers": {"with_layers": _example("Also the language and vision layers", True)},
    "summary": {"without_summary": _example("Just the version (sensor-rate streams)", False)},
}

#: Parameters whose examples depend on the operation: {operation id: {parameter name: examples}}.
OPERATION_PARAMETER_EXAMPLES: dict[str, dict[str, dict[str, dict[str, Any]]]] = {
    "get_belief": {
        "format": {
            "summary": _example("The posterior summary (JSON)", "summary"),
            "grid": _example("The whole posterior (msgpack)", "grid"),
        }
    },
    "normalize_scene_graph": {
        "format": {"region_grouped": _example("The region-grouped serialization", "region_grouped")}
    },
    # The fields that go beside a Spark-DSG binary body.
    "create_session": {
        "robot_id": {"robot": _example("The robot the session is for", "robot-7")},
        "grid": {"voxel_size": _example("A 0.25 m grid (JSON text)", '{"voxel_size": 0.25}')},
    },
    "ground": {"utterance": {"place": _example("Where the target was left", "my backpack is on the table")}},
}


def add_request_examples(spec: dict[str, Any]) -> dict[str, Any]:
    """Write the examples into an OpenAPI document (in place; returned). An operation id or media type of
    `BODY_EXAMPLES` that the document lacks is an error, so that examples cannot go stale unnoticed."""
    operations = {
        op["operationId"]: op for methods in spec.get("paths", {}).values() for op in methods.values()
    }
    for operation_id, examples in BODY_EXAMPLES.items():
        if operation_id not in operations:
            msg = f"request examples for an unknown operation {operation_id!r}"
            raise KeyError(msg)
        content = operations[operation_id].get("requestBody", {}).get("content", {})
        if "application/json" not in content:
            msg = f"operation {operation_id!r} takes no JSON body to give examples of"
            raise KeyError(msg)
        content["application/json"]["examples"] = copy.deepcopy(examples)
    for operation_id, op in operations.items():
        own = OPERATION_PARAMETER_EXAMPLES.get(operation_id, {})
        for parameter in op.get("parameters", []):
            name = parameter["name"]
            key = name.lower() if parameter.get("in") == "header" else name
            named = own.get(name) or PARAMETER_EXAMPLES.get(key)
            if named is not None:
                parameter["examples"] = copy.deepcopy(named)
    return spec
