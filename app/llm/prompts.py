"""The chat messages sent to the LLM: the hypothesis proposer's and the two foundation-model baselines'.

The wording is this project's; the JSON contracts are the reference's (its appendices "Hypothesis Generation
LLM Prompt" and "Foundation Model Baseline Prompts"):

- the map goes in as the region-grouped JSON of `app.scene_graph.region_grouped.to_region_grouped`
  (centres rounded to the millimetre, volumes to 4 significant digits, to keep prompts short);
- hypotheses come back as ``{"hypotheses": [{"utterance", "referred_object_id": [ids], "region_id": int,
  "confidence"}]}``, 1 to 5 of them, relations near/between/above/below/in/on, existing ids only;
- Scaffolded-LLM answers one Gaussian per given hypothesis, ``{"mu": [x, y, z], "sigma": [[3x3]],
  "explanation"}``; LLM-E2E answers the whole mixture, ``{"components": [{"mu", "sigma", "weight",
  "explanation"}]}``.

The hypothesis prompt carries one worked example (a scene and answer made up for this project), passed as
a user/assistant exchange before the real question. Every text a user supplied (the remark, labels, ids,
region names, a hypothesis's wording) goes in as a JSON string literal, like the map itself, so that quotes or
line breaks in it cannot pass for the prompt's own structure.
"""

from __future__ import annotations

import json
from typing import Any

from app.grounding.hypotheses import Hypothesis
from app.scene_graph.model import Region, SceneGraph, SceneObject
from app.scene_graph.region_grouped import region_integer_ids, to_region_grouped

#: The relations the LLM may use; the proposer maps synonyms ("under", "on top of") onto these.
LLM_RELATIONS = ("near", "between", "above", "below", "in", "on")
MAX_HYPOTHESES = 5

Message = dict[str, str]

HYPOTHESIS_SYSTEM_PROMPT = """\
You help a robot read remarks about where things are. The robot's map is a scene graph: rooms (regions), \
each listing its objects by id with a class name, a centre (x, y, z in metres, z up) and a volume (m^3). \
A remark mentions a target object that is NOT in the map and places it relative to objects that are.

List the readings of the remark that this map allows. Each reading has four fields:
- "utterance": the reading as a plain sentence, "there is a <target> <relation> <anchor object(s)>", \
with the target named as in the remark.
- "referred_object_id": a list of the anchor objects' ids: exactly one id for near, on, in, above and \
below; exactly two different ids for between.
- "region_id": the integer region_id of the region the anchor(s) belong to. Both anchors of a "between" \
reading must be in that same region.
- "confidence": a number from 0 to 1, how likely this reading is given the map.

Rules:
- Use only ids that appear in the map. Never make up an object or an id.
- Use only these relations: near, between, above, below, in, on.
- Answer with a single JSON object, {"hypotheses": [...]}, and nothing else."""

HYPOTHESIS_USER_TEMPLATE = """\
Map (objects grouped by region):
{scene_json}

Remark: {utterance}

Give between 1 and {max_hypotheses} readings. Give just one when a single object fits the remark; add \
readings only for other objects that fit it as well (the same kind of object elsewhere, a room the remark \
leaves open). Spread confidence by how usual each placement would be in a home: where people tend to \
leave such a thing, in which room."""

SCAFFOLDED_SYSTEM_PROMPT = """\
You estimate where an object is, in 3-D, for a robot. You get the robot's map as a scene graph (objects \
grouped by region, each with an id, a class name, a centre x, y, z in metres with z up, and a volume in \
m^3), a remark that mentions a target object not in the map, and the reading of that remark to use: which \
anchor object(s) and relation it refers to. Take that reading as correct.

Answer with the position of the TARGET object's centre as a 3-D Gaussian in the map's frame, as one JSON \
object and nothing else:
{"mu": [x, y, z], "sigma": [[sxx, sxy, sxz], [sxy, syy, syz], [sxz, syz, szz]], "explanation": "..."}

sigma is a covariance matrix in m^2: symmetric, positive semi-definite. Make it small for tight \
relations (on, in: standard deviations of 0.05 to 0.2 m) and large for loose ones (near: 0.5 to 2 m)."""

SCAFFOLDED_USER_TEMPLATE = """\
Map (objects grouped by region):
{scene_json}

Remark: {utterance}

Reading to use: {reading}
Region: {region_name} (region_id {region_id})
Anchor object(s):
{anchors}"""

E2E_SYSTEM_PROMPT = """\
You estimate where an object is, in 3-D, for a robot. You get the robot's map as a scene graph (objects \
grouped by region, each with an id, a class name, a centre x, y, z in metres with z up, and a volume in \
m^3) and a remark that mentions a target object not in the map. Nobody tells you which objects the remark \
refers to: work that out yourself.

Answer with the position of the TARGET object's centre as a mixture of 3-D Gaussians in the map's frame, \
one component per plausible reading of the remark, as one JSON object and nothing else:
{"components": [{"mu": [x, y, z], "sigma": [[sxx, sxy, sxz], [sxy, syy, syz], [sxz, syz, szz]], \
"weight": 0.6, "explanation": "..."}]}

Give 1 to 5 components. Weights are non-negative and add up to 1. Each sigma is a covariance matrix in \
m^2: symmetric, positive semi-definite."""

E2E_USER_TEMPLATE = """\
Map (objects grouped by region):
{scene_json}

Remark: {utterance}

Give at most {max_components} components."""


def _example_scene() -> SceneGraph:
    """A made-up flat: a hallway and a bedroom, each with a shoe rack, so that the remark is ambiguous."""

    def obj(oid: str, label: str, center: list[float], size: list[float], region: str) -> SceneObject:
        return SceneObject(id=oid, label=label, center=center, size=size, region_id=region)

    return SceneGraph(
        regions=[
            Region(id="0", name="Hallway", center=[1.0, 1.0, 1.2], size=[2.5, 2.5, 2.4]),
            Region(id="1", name="Bedroom", center=[4.2, 1.2, 1.2], size=[3.5, 3.0, 2.4]),
        ],
        objects=[
            obj("0", "shoe rack", [0.4, 1.2, 0.25], [0.8, 0.3, 0.5], "0"),
            obj("1", "coat stand", [1.6, 1.9, 0.9], [0.4, 0.4, 1.8], "0"),
            obj("2", "door", [0.0, 2.1, 1.0], [0.9, 0.1, 2.0], "0"),
            obj("3", "bench", [1.0, 0.3, 0.22], [1.0, 0.35, 0.45], "0"),
            obj("4", "bed", [4.0, 1.0, 0.3], [1.6, 2.0, 0.6], "1"),
            obj("5", "wardrobe", [5.4, 2.3, 1.0], [1.2, 0.6, 2.0], "1"),
            obj("6", "shoe rack", [4.6, 2.4, 0.2], [0.6, 0.3, 0.4], "1"),
            obj("7", "nightstand", [3.0, 0.3, 0.3], [0.45, 0.4, 0.6], "1"),
        ],
    )


_EXAMPLE_UTTERANCE = "I think I left my umbrella next to the shoe rack"
_EXAMPLE_ANSWER = {
    "hypotheses": [
        {
            "utterance": "there is an umbrella near the shoe rack",
            "referred_object_id": ["0"],
            "region_id": 0,
            "confidence": 0.75,
        },
        {
            "utterance": "there is an umbrella near the shoe rack",
            "referred_object_id": ["6"],
            "region_id": 1,
            "confidence": 0.25,
        },
    ]
}


def quoted(text: str) -> str:
    """A user's text as the prompts show it: one JSON string literal (see the module docstring)."""
    return json.dumps(text, ensure_ascii=False)


def scene_json(scene_graph: SceneGraph) -> str:
    """The map as the prompts show it: region-grouped JSON, numbers rounded (see the module docstring)."""
    grouped = to_region_grouped(scene_graph)
    for region in grouped.values():
        for entry in region["objects"].values():
            entry["center"] = [round(float(c), 3) for c in entry["center"]]
            entry["volume"] = float(f"{entry['volume']:.4g}")
    return json.dumps(grouped, ensure_ascii=False)


def hypothesis_messages(
    scene_graph: SceneGraph, utterance: str, max_hypotheses: int = MAX_HYPOTHESES
) -> list[Message]:
    """System prompt, the worked example as a user/assistant exchange, then the real question."""
    if not 1 <= max_hypotheses <= MAX_HYPOTHESES:
        msg = f"max_hypotheses must be between 1 and {MAX_HYPOTHESES}, got {max_hypotheses}"
        raise ValueError(msg)
    example_question = HYPOTHESIS_USER_TEMPLATE.format(
        scene_json=scene_json(_example_scene()),
        utterance=quoted(_EXAMPLE_UTTERANCE),
        max_hypotheses=MAX_HYPOTHESES,
    )
    question = HYPOTHESIS_USER_TEMPLATE.format(
        scene_json=scene_json(scene_graph), utterance=quoted(utterance), max_hypotheses=max_hypotheses
    )
    return [
        {"role": "system", "content": HYPOTHESIS_SYSTEM_PROMPT},
        {"role": "user", "content": example_question},
        {"role": "assistant", "content": json.dumps(_EXAMPLE_ANSWER)},
        {"role": "user", "content": question},
    ]


def scaffolded_messages(scene_graph: SceneGraph, utterance: str, hypothesis: Hypothesis) -> list[Message]:
    """The per-hypothesis Gaussian question of the Scaffolded-LLM baseline."""
    anchors = [scene_graph.object(i) for i in hypothesis.anchor_ids]
    region_id = anchors[0].region_id
    region_name = scene_graph.region(region_id).name if region_id is not None else "none"
    integer_id = region_integer_ids(scene_graph).get(region_id, -1) if region_id is not None else -1
    anchor_lines = "\n".join(
        f"- id {quoted(o.id)}: {quoted(o.label)}, centre {[round(c, 3) for c in o.center]}, "
        f"size {[round(s, 3) for s in o.size]}"
        for o in anchors
    )
    reading = hypothesis.text or f"the target is {hypothesis.relation.value} " + " and ".join(
        f"{o.label} {o.id}" for o in anchors
    )
    content = SCAFFOLDED_USER_TEMPLATE.format(
        scene_json=scene_json(scene_graph),
        utterance=quoted(utterance),
        reading=f"{quoted(reading)} (relation: {hypothesis.relation.value})",
        region_name=quoted(region_name),
        region_id=integer_id,
        anchors=anchor_lines,
    )
    return [{"role": "system", "content": SCAFFOLDED_SYSTEM_PROMPT}, {"role": "user", "content": content}]


def e2e_messages(
    scene_graph: SceneGraph, utterance: str, max_components: int = MAX_HYPOTHESES
) -> list[Message]:
    """The whole-mixture question of the LLM-E2E baseline."""
    content = E2E_USER_TEMPLATE.format(
        scene_json=scene_json(scene_graph), utterance=quoted(utterance), max_components=max_components
    )
    return [{"role": "system", "content": E2E_SYSTEM_PROMPT}, {"role": "user", "content": content}]


def example_exchange() -> dict[str, Any]:
    """The worked example (scene, remark, answer), for tests and documentation."""
    return {"scene_graph": _example_scene(), "utterance": _EXAMPLE_UTTERANCE, "answer": _EXAMPLE_ANSWER}
