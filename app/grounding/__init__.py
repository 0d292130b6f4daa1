"""Language grounding: hypotheses (which anchor, which relation) and their Gaussian mixture."""
