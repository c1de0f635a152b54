"""Multi-run commands on Dask (a LocalCluster of 2 worker processes; tests/test_sweep.py checks that
one gives the serial sweep's JSON): a run that fails does not stop the other, two processes never compute one version
twice, cuda runs go to the worker that offers a GPU, and stages that runs share are computed once
before they fan out."""
from __future__ import annotations

import sys
import time
import types
from pathlib import Path

import pytest

import runner
import pipeline
from runner import executor
from tests.test_pipeline import FAST_SYNTH

distributed = pytest.importorskip("distributed")

@pytest.fixture(scope="module")
def cluster():
    """(address for --executor, the address of the one worker that offers a GPU resource)."""
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, dashboard_address=":0") as local, \
            distributed.Client(local) as client:
        gpu_worker = sorted(local.scheduler_info["workers"])[0]

        async def offer_gpu(dask_worker):
            await dask_worker.set_resources(GPU=1)

        client.run(offer_gpu, workers=[gpu_worker])
        yield "dask://" + local.scheduler_address.removeprefix("tcp://"), gpu_worker


def test_a_run_that_fails_does_not_stop_the_other(cluster, tmp_path, capsys):
    too_few = tmp_path / "two_photos"
    too_few.mkdir()
    for name in ("a.png", "b.png"):
        (too_few / name).write_bytes(_png())
    artifacts = tmp_path / "artifacts"
    args = ["run", "--scene", str(too_few), "--scene", "synthetic", "--until", "ground_truth",
            "--artifacts", str(artifacts), "--executor", cluster[0], *[a for s in FAST_SYNTH for a in ("--set", s)]]
    assert pipeline.main(args) == 1
    out, err = capsys.readouterr()
    assert "synthetic: 2 stages, 2 ran" in out
    assert f"{too_few}: FAILED: stage ingest failed: SceneError" in err
    assert err.strip().splitlines()[-1].startswith(f"error: 1 of 2 failed: {too_few} (stage ingest failed")
    assert runner.Store(artifacts, "synthetic").current("ground_truth") is not None
    # a rerun picks up from the cache
    assert pipeline.main([*args[:1], *args[3:]]) == 0
    assert "synthetic: 2 stages, 0 ran (0 s), 2 cached" in capsys.readouterr().out


def _png() -> bytes:
    import io

    import numpy as np
    from PIL import Image

    buffer = io.BytesIO()
    Image.fromarray(np.full((32, 32, 3), 128, np.uint8)).save(buffer, format="PNG")
    return buffer.getvalue()


def run_when_both_are_ready(barrier: Path, artifacts: Path):
    """A task: wait until the other task is as far, then run the same stages, whose first one takes
    2 s longer than it would (longer than the two tasks' start can differ)."""
    import distributed

    import stages.ingest as ingest

    runner.status("synthetic", overrides=FAST_SYNTH, artifacts=artifacts)  # imports, code hashes: as far as a run goes
    barrier.mkdir(exist_ok=True)
    (barrier / distributed.get_worker().address.replace("/", "_")).touch()
    while len(list(barrier.iterdir())) < 2:
        time.sleep(0.01)
    real = ingest.run
    ingest.run = lambda ctx: (time.sleep(2), real(ctx))
    try:
        return runner.run("synthetic", until="ground_truth", overrides=FAST_SYNTH, artifacts=artifacts)
    finally:
        ingest.run = real


def test_two_tasks_never_compute_one_version_twice(cluster, tmp_path):
    with distributed.Client(cluster[0].replace("dask://", "tcp://")) as client:
        workers = sorted(client.scheduler_info()["workers"])
        futures = [client.submit(run_when_both_are_ready, tmp_path / "barrier", tmp_path / "artifacts",
                                 workers=[w], pure=False) for w in workers]
        first, second = client.gather(futures)
    assert first.fingerprints == second.fingerprints
    for stage in ("ingest", "ground_truth"):  # one computed it, the other waited for it and reused it
        assert sorted([first[stage], second[stage]]) == ["computed", "reused"], (first, second)
    versions = [p for p in (tmp_path / "artifacts" / "synthetic" / "ingest").iterdir() if not p.name.startswith(".")]
    assert sorted(p.name for p in versions) == sorted(["current", first.fingerprints["ingest"]])


def test_cuda_runs_ask_for_the_gpu_worker(cluster, tmp_path):
    # ingest does not touch the device, so these runs succeed on a machine without one
    specs = [executor.RunSpec(f"synthetic-{seed} on cuda", f"synthetic-{seed}",
                              dict(until="ingest", overrides=[*FAST_SYNTH, "run.device=cuda"],
                                   artifacts=tmp_path / "artifacts")) for seed in (1, 2, 3)]
    outcomes = list(executor.run_all(specs, cluster[0]))
    assert [o.error for o in outcomes] == [None] * 3
    assert {o.where for o in outcomes} == {cluster[1]}


def test_slurm_starts_a_jobqueue_cluster_of_the_workers_asked_for(monkeypatch, tmp_path, capsys):
    """dask-jobqueue's SLURMCluster, replaced by an in-process cluster: what `--executor slurm` asks of it."""
    scaled = []  # what the cluster was asked for: its config, then its workers (closing it scales it to 0)

    class FakeSLURMCluster(distributed.LocalCluster):
        def __init__(self, config_name=None):
            scaled.append(config_name)
            super().__init__(n_workers=0, processes=False, threads_per_worker=1, dashboard_address=":0",
                             resources={"GPU": 1})

        def scale(self, n=0, **kwargs):
            scaled.append(n)
            return super().scale(n, **kwargs)

    monkeypatch.setitem(sys.modules, "dask_jobqueue", types.SimpleNamespace(SLURMCluster=FakeSLURMCluster))
    spec = executor.RunSpec("synthetic", "synthetic", dict(until="ingest", overrides=[*FAST_SYNTH, "run.device=cuda"],
                                                           artifacts=tmp_path / "artifacts"))
    [outcome] = executor.run_all([spec], "slurm:gpu-nodes", workers=1)
    assert outcome.error is None and outcome.report == {"ingest": "computed"} and scaled[:2] == ["gpu-nodes", 1]
    assert "dask: FakeSLURMCluster, 1 workers" in capsys.readouterr().err


def test_shared_stages_are_planned_once_per_scene(tmp_path):
    artifacts = tmp_path / "artifacts"

    def spec(name, scene="synthetic", **args):
        return executor.RunSpec(name, scene, {"artifacts": artifacts, "overrides": FAST_SYNTH, **args})

    alpha = [spec(f"alpha {a}", overrides=[*FAST_SYNTH, f"schedule.alpha={a}"]) for a in (0.5, 0.65)]
    barf, colmap = spec("neus-barf", preset="neus-barf"), spec("neus-colmap", preset="neus-colmap")
    plan = executor.plan([*alpha, barf, colmap, spec("other scene", "synthetic-3")])
    ((where, steps),) = plan.preparations.items()  # the other scene shares nothing: no preparation
    assert where[1] == "synthetic"
    # every stage alpha does not reach is shared by all; the uniform schedule (and what follows it,
    # the GT-pose surface excepted) by the two baselines only: prepared once, with the first that has it
    (first, common), (_, uniform) = steps
    assert first.name == "alpha 0.5" and "schedule" not in common
    assert {"ingest", "features", "spectral", "reference", "reference_surface"} <= set(common)
    assert uniform[0] == "schedule" and "anchors" not in uniform  # the two baselines' anchors differ
    assert plan.shared["alpha 0.65"] == set(common) and plan.shared["neus-colmap"] == set(common) | {"schedule"}
    assert plan.shared["other scene"] == set()
    with pytest.raises(ValueError, match="two runs share a name"):
        executor.plan([alpha[0], alpha[0]])
