import dataclasses
import re

import numpy as np
import pytest

from app.grounding.geometric import FixedGrounder, GeometricConfig, GeometricGrounder
from app.grounding.hypotheses import Hypothesis
from app.grounding.relations import Relation
from app.scene_graph.model import SceneGraph


@pytest.fixture
def room() -> SceneGraph:
    """A table (top at 0.75 m) standing on the floor, a shelf hanging on a wall, a sofa and a chair."""
    return SceneGraph.model_validate(
        {
            "objects": [
                {"id": "table", "label": "table", "center": [0, 0, 0.375], "size": [1.2, 0.8, 0.75]},
                {"id": "shelf", "label": "shelf", "center": [3, 0, 1.5], "size": [1.0, 0.3, 0.1]},
                {"id": "sofa", "label": "sofa", "center": [0, 3, 0.4], "size": [2.0, 0.9, 0.8]},
                {"id": "chair", "label": "chair", "center": [0, -3, 0.45], "size": [0.5, 0.5, 0.9]},
            ]
        }
    )


def _one(room: SceneGraph, relation: Relation, *anchors: str) -> tuple[np.ndarray, np.ndarray]:
    ((g,),) = (
        d.components for d in GeometricGrounder().ground(room, "", [Hypothesis(tuple(anchors), relation)])
    )
    assert np.allclose(g.covariance, g.covariance.T)
    assert np.linalg.eigvalsh(g.covariance).min() > 0
    return g.mean, g.covariance


def test_on_sits_on_the_top_surface_spread_over_the_footprint(room: SceneGraph) -> None:
    mean, cov = _one(room, Relation.ON, "table")
    np.testing.assert_allclose(mean, [0, 0, 0.75 + 0.1])
    np.testing.assert_allclose(np.diag(cov)[:2], [1.2**2 / 12, 0.8**2 / 12])


def test_in_is_the_box_itself(room: SceneGraph) -> None:
    mean, cov = _one(room, Relation.IN, "sofa")
    np.testing.assert_allclose(mean, [0, 3, 0.4])
    np.testing.assert_allclose(np.diag(cov), np.array([2.0, 0.9, 0.8]) ** 2 / 12)


def test_below_a_standing_table_is_on_the_floor_and_below_a_shelf_is_beneath_it(room: SceneGraph) -> None:
    table_mean, _ = _one(room, Relation.BELOW, "table")
    shelf_mean, _ = _one(room, Relation.BELOW, "shelf")
    assert table_mean[2] == pytest.approx(0.1)  # floor (z=0) plus a small object's half height
    assert shelf_mean[2] == pytest.approx(1.45 - 0.3)


def test_near_is_wider_than_on_and_above_is_higher(room: SceneGraph) -> None:
    _, on_cov = _one(room, Relation.ON, "table")
    _, near_cov = _one(room, Relation.NEAR, "table")
    above_mean, _ = _one(room, Relation.ABOVE, "table")
    assert np.trace(near_cov) > np.trace(on_cov)
    assert above_mean[2] > 0.75 + 0.1


def test_between_spreads_along_the_segment_and_is_narrow_across(room: SceneGraph) -> None:
    mean, cov = _one(room, Relation.BETWEEN, "sofa", "chair")
    np.testing.assert_allclose(mean, [0, 0, 0.425])
    eigvals, eigvecs = np.linalg.eigh(cov)
    along = eigvecs[:, -1]
    assert abs(along[1]) == pytest.approx(1.0, abs=1e-3)  # the sofa-chair axis is (almost) y
    assert eigvals[-1] == pytest.approx(6.0**2 / 12, rel=1e-3)
    assert eigvals[0] == pytest.approx(0.3**2, rel=1e-3)


def test_yawed_anchor_rotates_the_footprint() -> None:
    sg = SceneGraph.model_validate(
        {
            "objects": [
                {
                    "id": "t",
                    "label": "table",
                    "center": [0, 0, 0.4],
                    "size": [2.0, 0.5, 0.8],
                    "yaw": np.pi / 2,
                }
            ]
        }
    )
    ((g,),) = (d.components for d in GeometricGrounder().ground(sg, "", [Hypothesis(("t",), Relation.ON)]))
    assert g.covariance[1, 1] == pytest.approx(4.0 / 12)
    assert g.covariance[0, 0] == pytest.approx(0.25 / 12)


def test_fixed_grounder_is_the_anchor_centroid_with_ten_centimetres(room: SceneGraph) -> None:
    ((g,),) = (d.components for d in FixedGrounder().ground(room, "", [Hypothesis(("table",), Relation.ON)]))
    np.testing.assert_allclose(g.mean, [0, 0, 0.375])
    np.testing.assert_allclose(g.covariance, np.eye(3) * 0.01)


def test_describe_has_a_stable_checksum() -> None:
    """The checksum is a function of the configuration: equal for equal configs (another instance, a config
    built anew), different when any spread changes."""
    described = GeometricGrounder().describe()
    assert re.fullmatch(r"sha256:[0-9a-f]{64}", described["checksum"])
    assert GeometricGrounder(GeometricConfig()).describe() == described
    for spread in dataclasses.fields(GeometricConfig):
        changed = GeometricConfig(**{spread.name: getattr(GeometricConfig(), spread.name) + 0.05})
        other = GeometricGrounder(changed).describe()
        assert other["config"][spread.name] != described["config"][spread.name]
        assert other["checksum"] != described["checksum"], spread.name
