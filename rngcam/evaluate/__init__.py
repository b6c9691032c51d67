"""Benchmarks: `rngcam bench` (every method on every scene under one time budget) and
`rngcam bench --stress` (the numerical-stability matrix)."""
