"""Benchmarks. Each module with `register(bench_subparsers)` adds a `trimeter bench <name>` command."""
