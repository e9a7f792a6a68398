"""Benchmarks: one module per area, each with ``run(quick: bool) -> dict`` (see labctl.cli.bench)."""
