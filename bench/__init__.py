"""Benchmarks and accuracy tables (run from the repository root: ``python -m bench.paper_scale``)."""
