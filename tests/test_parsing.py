import pytest

from app.grounding.parsing import parse_utterance
from app.grounding.relations import Relation

CASES = [
    ("I left my backpack on the table", "backpack", Relation.ON, ("table",), None),
    ("The mug is next to the sink", "mug", Relation.NEAR, ("sink",), None),
    ("the remote is beside the couch", "remote", Relation.NEAR, ("couch",), None),
    ("my keys are by the door", "keys", Relation.NEAR, ("door",), None),
    ("There is a box under the desk", "box", Relation.BELOW, ("desk",), None),
    ("the cat toy is beneath the bed", "cat toy", Relation.BELOW, ("bed",), None),
    ("it's on top of the dresser", "", Relation.ON, ("dresser",), None),
    ("my wallet is inside the drawer", "wallet", Relation.IN, ("drawer",), None),
    ("the clock is above the tv", "clock", Relation.ABOVE, ("tv",), None),
    ("the lamp hangs over the table", "lamp", Relation.ABOVE, ("table",), None),
    (
        "look for the lamp between the sofa and the armchair",
        "lamp",
        Relation.BETWEEN,
        ("sofa", "armchair"),
        None,
    ),
    ("find the chair closest to the door", "chair", Relation.CLOSEST, ("door",), None),
    ("the bag is near the table in the kitchen", "bag", Relation.NEAR, ("table",), "kitchen"),
    ("I put my phone on one of the chairs", "phone", Relation.ON, ("chairs",), None),
]


@pytest.mark.parametrize(("utterance", "target", "relation", "anchors", "region"), CASES)
def test_parse(
    utterance: str, target: str, relation: Relation, anchors: tuple[str, ...], region: str | None
) -> None:
    parse = parse_utterance(utterance, region_names=("kitchen", "bedroom"))
    assert (parse.target, parse.relation, parse.anchor_phrases, parse.region_phrase) == (
        target,
        relation,
        anchors,
        region,
    )


def test_unknown_region_stays_part_of_the_anchor_phrase() -> None:
    parse = parse_utterance("the bag is near the table in the garage", region_names=("kitchen",))
    assert parse.anchor_phrases == ("table in the garage",)
    assert parse.region_phrase is None


def test_no_relation_word_means_no_anchor() -> None:
    parse = parse_utterance("where is my backpack")
    assert parse.anchor_phrases == ()
    assert parse.target == "backpack"
