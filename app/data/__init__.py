"""Grounding cases: the evaluation file format, the builder from real layouts, and converters."""
