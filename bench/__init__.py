"""Benchmark scripts, run from the repository root as modules: ``python -m bench.bench_sdf`` (see bench/README.md)."""
