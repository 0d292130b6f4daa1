"""Language grounding: hypotheses (which anchor, which relation) and their Gaussian mixture.

A namespace of modules, re-exporting nothing: the belief and the stores import `mixture` alone, and
package-level re-exports would import the proposers, the parser and the vocabulary with it. Other rooms
import from the defining module:

- `mixture`: `GaussianMixture`, `Gaussian`, `UniformBox`, `map_box`, `project_to_pd`;
- `relations`: `Relation`, `RELATION_PHRASES`; `hypotheses`: `Hypothesis`, `Proposal`;
- `interfaces`: the `Grounder` and `HypothesisProposer` protocols;
- `sensor`: `LanguageSensor` (proposer + grounder -> one mixture) and its `Grounding`;
- the proposers and grounders: `builtin.BuiltinProposer` (with `ProposerParams`), `lexical.LexicalProposer`,
  `geometric.GeometricGrounder` and `FixedGrounder`;
- `parsing`: `parse_utterance`, `target_noun`; `box_relations`: the box relations and their thresholds,
  shared by the proposer, the LSM's features and the case builder.
"""
