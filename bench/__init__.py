"""Benchmarks run by `make bench`; they print figures, they never assert timings."""
