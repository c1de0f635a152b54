"""Benchmark, sweep and report scripts. A package so that `from bench import bench` finds
bench/bench.py the same way from tests and from the scripts (which put the repository root first
on sys.path); without it, a script's own folder on sys.path would shadow the package."""
