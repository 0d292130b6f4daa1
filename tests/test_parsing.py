import numpy as np
import pytest

from app.data.templates import LABEL_SYNONYMS, RELATION_PHRASES, SR3D_PHRASES, VLA3D_PHRASES, render_utterance
from app.grounding.parsing import parse_utterance, split_attributes
from app.grounding.relations import Relation

REGIONS = ("kitchen", "bedroom", "living room")

# utterance, target, relation, anchor phrases, region
CASES = [
    ("I left my backpack on the table", "backpack", Relation.ON, ("table",), None),
    ("The mug is next to the sink", "mug", Relation.NEAR, ("sink",), None),
    ("the remote is beside the couch", "remote", Relation.NEAR, ("couch",), None),
    ("my keys are by the door", "keys", Relation.NEAR, ("door",), None),
    ("There is a box under the desk", "box", Relation.BELOW, ("desk",), None),
    ("the cat toy is beneath the bed", "cat toy", Relation.BELOW, ("bed",), None),
    ("the shoes are below the bench", "shoes", Relation.BELOW, ("bench",), None),
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
    # region mentions anywhere, with storeys; a room word that is part of a label stays in the anchor
    ("the mug is in the kitchen on the counter", "mug", Relation.ON, ("counter",), "kitchen"),
    (
        "my book is on the nightstand in the upstairs bedroom",
        "book",
        Relation.ON,
        ("nightstand",),
        "upstairs bedroom",
    ),
    ("the keys are on the table upstairs", "keys", Relation.ON, ("table",), "upstairs"),
    ("the cup is in the kitchen cabinet", "cup", Relation.IN, ("kitchen cabinet",), None),
    ("the pillow is on the sofa in the living room", "pillow", Relation.ON, ("sofa",), "living room"),
    ("the bag is in the kitchen", "bag", Relation.NEAR, (), "kitchen"),
    # attributes stay on the anchor phrase
    ("the remote is on the small table", "remote", Relation.ON, ("small table",), None),
    ("the mug is on the white cabinet", "mug", Relation.ON, ("white cabinet",), None),
    # plurals, "the other", alternatives, nested relations
    ("the lamp is between the chairs", "lamp", Relation.BETWEEN, ("chairs",), None),
    ("the lamp is between the chair and the other chair", "lamp", Relation.BETWEEN, ("chair", "chair"), None),
    ("the keys are on the table or the desk", "keys", Relation.ON, ("table", "desk"), None),
    ("the cup is on the table by the window", "cup", Relation.ON, ("table",), None),
    # fronted sentences and lead-ins of the generated data
    ("right above the shelf there is a book", "book", Relation.ABOVE, ("shelf",), None),
    (
        "check between the keyboard and the box for the mouse",
        "mouse",
        Relation.BETWEEN,
        ("keyboard", "box"),
        None,
    ),
    ("my chair is the one furthest away from the door", "chair", Relation.FARTHEST, ("door",), None),
    ("the armchair should be near to the railing", "armchair", Relation.NEAR, ("railing",), None),
    ("the plates are stored in the cupboard", "plates", Relation.IN, ("cupboard",), None),
    ("I'm pretty sure my mug is just under the shelf", "mug", Relation.BELOW, ("shelf",), None),
    ("you'll find the towel up above the bathtub", "towel", Relation.ABOVE, ("bathtub",), None),
    ("there's a mug on the counter", "mug", Relation.ON, ("counter",), None),
    ("the cup that is on the table", "cup", Relation.ON, ("table",), None),
    ("the cat is sleeping in the box", "cat", Relation.IN, ("box",), None),
    ("Could you find my wallet? It's under the sofa", "wallet", Relation.BELOW, ("sofa",), None),
    # A word saying which one of its kind the anchor is keeps the relation (29 dev descriptions).
    ("the book is on the top shelf", "book", Relation.ON, ("shelf",), None),
    ("the window nearest the front doors", "window", Relation.CLOSEST, ("doors",), None),
    ("the desk is under the right window", "desk", Relation.BELOW, ("window",), None),
    ("the mug is in the top cabinet", "mug", Relation.IN, ("cabinet",), None),
]


@pytest.mark.parametrize(("utterance", "target", "relation", "anchors", "region"), CASES)
def test_parse(
    utterance: str, target: str, relation: Relation, anchors: tuple[str, ...], region: str | None
) -> None:
    parse = parse_utterance(utterance, region_names=REGIONS)
    assert (parse.target, parse.relation, parse.anchor_phrases, parse.region_phrase) == (
        target,
        relation,
        anchors,
        region,
    )
    assert parse.relation_known


@pytest.mark.parametrize(
    "utterance",
    ["the chair furthest to the right", "the trash can closest to you", "select the stool nearest you"],
)
def test_a_side_or_the_listener_is_no_anchor(utterance: str) -> None:
    """Not "to" (of "to the right") nor "you": words that name no object of the map."""
    assert parse_utterance(utterance).anchor_phrases == ()


@pytest.mark.parametrize("table", [RELATION_PHRASES, SR3D_PHRASES, VLA3D_PHRASES])
def test_every_phrase_the_case_builder_says_reads_back_as_its_relation(
    table: dict[Relation, tuple[str, ...]],
) -> None:
    """VLA-3D's "most distant from" had read as an unknown "near". Sr3D says "close to" and "near" for its
    closest (its own wording), which the parser reads as near by design: the proposer adds the closest."""
    for relation, phrases in table.items():
        anchor = "the sofa and the armchair" if relation is Relation.BETWEEN else "the table"
        for phrase in phrases:
            if table is SR3D_PHRASES and relation is Relation.CLOSEST and phrase in ("close to", "near"):
                continue
            parse = parse_utterance(f"the mug that is {phrase} {anchor}")
            assert (parse.relation, parse.relation_known) == (relation, True), phrase


def test_attribute_words_are_listed() -> None:
    parse = parse_utterance("the mug is on the small white table")
    assert parse.anchor_phrases == ("small white table",)
    assert parse.attributes == ("small", "white")
    # The last word is the noun even when it could be an attribute.
    assert parse_utterance("the mug is next to the glass").attributes == ()


@pytest.mark.parametrize(
    ("utterance", "target", "anchor"),
    [
        ("the keys are behind the tv", "keys", "tv"),
        ("my phone is in front of the couch", "phone", "couch"),
        ("the box is to the left of the door", "box", "door"),
        ("the book is at the desk", "book", "desk"),
        ("the ball is halfway up the stairs", "ball", "stairs"),  # no listed phrase: the copula fallback
    ],
)
def test_unknown_relation_words_read_as_near_with_a_flag(utterance: str, target: str, anchor: str) -> None:
    parse = parse_utterance(utterance)
    assert (parse.target, parse.relation, parse.anchor_phrases) == (target, Relation.NEAR, (anchor,))
    assert parse.relation_phrase == ""
    assert not parse.relation_known


def test_room_words_are_regions_even_when_the_map_does_not_name_them() -> None:
    parse = parse_utterance("the bag is near the table in the garage", region_names=("kitchen",))
    assert (parse.anchor_phrases, parse.region_phrase) == (("table",), "garage")


def test_no_relation_word_means_no_anchor() -> None:
    parse = parse_utterance("where is my backpack")
    assert parse.anchor_phrases == ()
    assert parse.target == "backpack"
    assert parse.relation_phrase == ""


@pytest.mark.parametrize("relation", list(Relation))
def test_generated_utterances_parse_back(relation: Relation) -> None:
    """Every template and phrase of the data generator reads back to its relation and anchor labels."""
    rng = np.random.default_rng(7)
    labels = ["table", "kitchen counter", "trash can", "sofa chair", "books", "light", "tv stand", "glass"]
    for _ in range(150):
        target, first, second = (labels[int(i)] for i in rng.integers(len(labels), size=3))
        anchors = (first, second)[: relation.n_anchors]
        utterance = render_utterance(relation, target, anchors, rng, portable=bool(rng.integers(2)))
        parse = parse_utterance(utterance)
        assert parse.relation is relation, utterance
        said = [{a, *LABEL_SYNONYMS.get(a, ())} for a in anchors]
        assert len(parse.anchor_phrases) == len(anchors), utterance
        assert all(p in s for p, s in zip(parse.anchor_phrases, said, strict=True)), utterance


def test_every_generator_phrase_is_read_as_its_relation() -> None:
    for relation, phrases in RELATION_PHRASES.items():
        for phrase in phrases:
            second = " and the sofa" if relation is Relation.BETWEEN else ""
            parse = parse_utterance(f"the mug is {phrase} the table{second}")
            assert (parse.relation, parse.anchor_phrases[0], parse.target) == (relation, "table", "mug"), (
                phrase
            )


# --- the whole utterance: mentions and how each constrains the target -------------------------------------


def _mentions(parse):
    return [(m.role, m.noun, m.relation, m.head) for m in parse.mentions]


def test_a_qualifier_of_the_anchor_says_which_table() -> None:
    parse = parse_utterance("the cup is on the table next to the tv")
    assert _mentions(parse) == [
        ("target", "cup", None, None),
        ("anchor", "table", Relation.ON, None),
        ("qualifier", "tv", Relation.NEAR, 1),
    ]
    assert parse.anchor_phrases == ("table",)


def test_a_multi_sentence_description_finds_its_relation_clause() -> None:
    parse = parse_utterance("this is a brown chair. it is at the end of the table close to the painting.")
    assert parse.target == "brown chair" and parse.target_attributes == ("brown",)
    assert parse.sentences == 2
    table = next(m for m in parse.mentions if m.noun == "table")
    assert (table.role, table.relation, table.relation_known, table.sentence) == (
        "anchor",
        Relation.NEAR,
        False,
        1,
    )
    painting = next(m for m in parse.mentions if m.noun == "painting")
    assert painting.role == "qualifier" and parse.mentions[painting.head].noun == "table"


def test_the_target_named_again_in_a_later_sentence_is_the_target() -> None:
    parse = parse_utterance("it is a black computer monitor. the black computer monitor sits on the desk.")
    assert [(m.role, m.noun) for m in parse.mentions] == [("target", "computer monitor"), ("anchor", "desk")]
    assert parse.relation is Relation.ON


@pytest.mark.parametrize(
    ("utterance", "relation"),
    [
        ("choose the chair that is closest to the door", Relation.CLOSEST),
        ("the table that is closer to the bench", Relation.CLOSEST),
        ("find the cabinet that is far away from the washing machine", Relation.FARTHEST),
        ("the chair that is far from the cabinets", Relation.FARTHEST),
        ("the box that is in the middle of the desk and the trash can", Relation.BETWEEN),
        ("select the table that is in the center of the armchair and the kitchen counter", Relation.BETWEEN),
        ("choose the box that is on top of the desk", Relation.ON),
        ("select the sink that is underneath the cabinet", Relation.BELOW),
    ],
)
def test_sr3d_statements_read_as_their_relation(utterance: str, relation: Relation) -> None:
    parse = parse_utterance(utterance)
    assert parse.relation is relation and parse.relation_known
    assert len(parse.anchor_phrases) == relation.n_anchors


def test_a_disjunction_names_two_alternative_anchors() -> None:
    parse = parse_utterance("my keys are on the bed or the couch")
    bed, couch = parse.anchors
    assert (bed.noun, couch.noun) == ("bed", "couch")
    assert bed.relation is couch.relation is Relation.ON
    assert couch.disjunct and not bed.disjunct


@pytest.mark.parametrize(
    "utterance",
    ["my keys are not on the table", "the keys aren't on the table", "my keys are never on the table"],
)
def test_negation_marks_the_anchor(utterance: str) -> None:
    (table,) = parse_utterance(utterance).anchors
    assert table.noun == "table" and table.negated


@pytest.mark.parametrize(
    "utterance",
    [
        "the mug that isn't mine is on the table",
        "the phone that doesn't work is on the table",
        "the remote i couldn't find is under the table",
    ],
)
def test_a_negation_in_another_clause_does_not_negate_the_relation(utterance: str) -> None:
    (table,) = parse_utterance(utterance).anchors
    assert table.noun == "table" and not table.negated


def test_a_negated_region_is_ruled_out_not_named() -> None:
    parse = parse_utterance("the mug is on the table, not in the kitchen")
    assert parse.region_phrase is None and parse.region_phrases == ()
    assert parse.excluded_region_phrases == ("kitchen",)
    assert parse_utterance("my mug isn't in the kitchen").excluded_region_phrases == ("kitchen",)
    kept = parse_utterance("the mug that isn't mine is in the kitchen")
    assert kept.region_phrases == ("kitchen",) and kept.excluded_region_phrases == ()


def test_a_storey_after_the_room_qualifies_it() -> None:
    parse = parse_utterance("the mug is on the table in the bedroom upstairs")
    assert parse.region_phrases == ("upstairs bedroom",)
    assert parse.anchor_phrases == ("table",)


def test_accents_and_full_width_letters_read_as_plain_ones() -> None:
    composed = parse_utterance("the remote is on the canap\u00e9")
    decomposed = parse_utterance("the remote is on the canape\u0301")
    assert composed.anchor_phrases == decomposed.anchor_phrases == ("canape",)
    wide = parse_utterance("\uff34\uff28\uff25 \uff2d\uff35\uff27 is on the table")
    assert wide.target == "mug" and wide.anchor_phrases == ("table",)


def test_a_qualifier_can_be_negated() -> None:
    parse = parse_utterance("the books on the highest shelf but not on top of the cabinet")
    shelf = next(m for m in parse.mentions if m.noun == "shelf")
    assert shelf.attributes == ("high",) and not shelf.negated
    cabinet = next(m for m in parse.mentions if m.noun == "cabinet")
    assert cabinet.negated


@pytest.mark.parametrize(
    "utterance",
    [
        "the box to the left of the door",
        "the chair behind the desk",
        "facing the bed, choose the nightstand on the left",
        "the lamp in front of the window",
    ],
)
def test_view_dependent_words_are_marked(utterance: str) -> None:
    parse = parse_utterance(utterance)
    assert parse.view_dependent
    assert any(m.view_dependent for m in parse.anchors)


@pytest.mark.parametrize(
    ("utterance", "target", "viewpoint"),
    [
        (
            "If you face the whiteboard with writing, the bench is the one on the right of the table.",
            "bench",
            "whiteboard",
        ),
        ("When standing by the sink, the towel is on the left", "towel", "sink"),
        ("With your back to the door, it is the window directly opposite you", "window", "door"),
        # A viewpoint said as a sentence of its own, or without a comma before the description.
        ("Face the window. The door you want is on the left.", "door", "window"),
        (
            "face the fridge and then move to the trash can on the ground in the left corner",
            "trash can",
            "fridge",
        ),
        (
            "Facing the wall with the drawing the box you are looking for is the one on the right",
            "box",
            "wall",
        ),
        ("Stand facing the sinks. The towel is on the left.", "towel", "sink"),
    ],
)
def test_the_objects_of_a_viewpoint_clause_are_view_dependent_anchors_not_the_target(
    utterance: str, target: str, viewpoint: str
) -> None:
    parse = parse_utterance(utterance)
    assert split_attributes(parse.target)[1] == target
    seen_from = next(m for m in parse.mentions if m.noun == viewpoint)
    assert seen_from.role == "anchor" and seen_from.view_dependent
    assert parse.view_dependent


@pytest.mark.parametrize(
    ("utterance", "noun"),
    [
        ("When facing the windows, the one on the left.", "window"),
        ("Facing the row of shoes, it is the rightmost pair.", "shoe"),
        (
            "When standing in the middle of the room facing the windows the correct one is on the left.",
            "window",
        ),
        ("Stand at the end of the bed. You want the one on the left.", "bed"),
    ],
)
def test_a_viewpoint_clause_names_the_target_when_nothing_else_does(utterance: str, noun: str) -> None:
    parse = parse_utterance(utterance)
    assert parse.mentions[next(k for k, m in enumerate(parse.mentions) if m.role == "target")].noun == noun
    assert not any(m.noun == noun for m in parse.anchors)


def test_stand_is_an_object_unless_it_opens_a_viewpoint() -> None:
    assert split_attributes(parse_utterance("the night stand is next to the bed").target)[1] == "night stand"
    assert (
        split_attributes(parse_utterance("Stand by the door. The lamp is on the left.").target)[1] == "lamp"
    )


@pytest.mark.parametrize(
    ("utterance", "relation"),
    [
        ("the closest keyboard to the whiteboard", Relation.CLOSEST),
        ("the farthest chair from the door", Relation.FARTHEST),
        ("my keys are by the nearest lamp to the door", Relation.CLOSEST),
        ("the chair is the closest one to the door", Relation.CLOSEST),
    ],
)
def test_a_superlative_before_the_name_relates_the_name_to_what_follows(
    utterance: str, relation: Relation
) -> None:
    parse = parse_utterance(utterance)
    said = {m.noun: m for m in parse.mentions}
    assert said["door" if "door" in said else "whiteboard"].relation is relation
    if "keys" not in utterance:
        assert split_attributes(parse.target)[1] in {"keyboard", "chair"}


def test_a_superlative_towards_a_side_is_not_split() -> None:
    parse = parse_utterance("the window is the farthest window to the right on the wall")
    assert split_attributes(parse.target)[1] == "window"
    assert not any(m.noun in {"to", "right"} for m in parse.mentions)


@pytest.mark.parametrize(
    ("utterance", "target"),
    [
        ("The can closest to the door.", "can"),
        ("Facing the cans, the white can on the left.", "can"),
        ("the small pink chair that can roll around", "chair"),
        ("you can find my keys on the table", "keys"),
    ],
)
def test_can_is_a_noun_after_a_determiner_or_an_attribute(utterance: str, target: str) -> None:
    assert split_attributes(parse_utterance(utterance).target)[1] == target


def test_looking_for_is_a_search_not_a_viewpoint() -> None:
    assert (
        split_attributes(parse_utterance("Looking for a blue couch, next to it is a table").target)[1]
        == "couch"
    )


def test_a_view_independent_utterance_is_not_view_dependent() -> None:
    parse = parse_utterance("the box next to the door")
    assert not parse.view_dependent and not any(m.view_dependent for m in parse.mentions)


def test_an_unknown_object_stays_an_unknown_mention() -> None:
    (spaceship,) = parse_utterance("the keys are next to the spaceship").anchors
    assert (spaceship.phrase, spaceship.known, spaceship.relation) == ("spaceship", False, Relation.NEAR)


def test_map_labels_join_the_vocabulary() -> None:
    assert not parse_utterance("the cup is next to the zorblax").anchors[0].known
    parse = parse_utterance("the cup is next to the zorblax", object_names=("zorblax",))
    assert parse.anchors[0].known


@pytest.mark.parametrize(
    "utterance", ["la taza está en la mesa", "die Tasse steht auf dem Tisch", "xq zv ptk"]
)
def test_text_that_is_not_english_says_so(utterance: str) -> None:
    assert not parse_utterance(utterance).english


def test_english_reads_as_english() -> None:
    assert parse_utterance("the backpack is in the kitchen on the table").english
