"""Benchmark, sweep and report scripts, run from the repository's root as modules
(``python -m bench.bench ...``), so that ``from bench import bench`` finds this package from the
scripts and the tests alike; the project itself (pipeline, runner, stages, manifoldneus) is installed."""
