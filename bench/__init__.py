"""Benchmark scripts: run each as `python -m bench.NAME` from the repository root (results in bench/*.md)."""
