"""One fingerprint, one result: the pipeline run twice from an empty cache writes the same
artifacts, and a run interrupted inside a successor round and resumed from its checkpoint ends
exactly where the uninterrupted run does. Tiny synthetic scene, CPU."""
from __future__ import annotations

import numpy as np
import pytest
import torch

import runner
from manifoldneus.data import artifacts as readers
from manifoldneus.data import io
from conftest import bitwise_on_cpu
from manifoldneus.neural.train import Trainer
from tests.test_end_to_end import TINY

pytestmark = bitwise_on_cpu

# a checkpoint every 10 iterations, so the interruption below falls between two of them
REPRO = [*TINY, "train.ckpt_every=10"]
UNTIL = "successors"  # and "reference" beside it: pycolmap is part of the fingerprint-one-result promise


def version(root, stage):
    store = runner.Store(root, "synthetic")
    return store.version_dir(stage, store.current(stage))


def outputs(root) -> dict:
    """What each stage up to the successors wrote that later stages read."""
    feats, _ = readers.load_features(version(root, "features"))
    matches, _ = readers.load_matches(version(root, "matching"))
    out = {"keypoints": [f["keypoints"] for f in feats], "matches": [matches[k] for k in sorted(matches)],
           "reference": io.load_arrays(version(root, "reference") / "poses.zarr")["w2c"],
           "schedule": readers.load_schedule(version(root, "schedule"))["round"]}
    for stage, rnd in (("anchors", "round_0"), ("successors", "final")):
        d = version(root, stage) / rnd
        out[f"{stage}_w2c"] = readers.load_round(d)["w2c"]
        model = torch.load(d / "model.pt", map_location="cpu", weights_only=False)
        out[f"{stage}_field"] = [t.numpy() for t in model["field"].values()]
    return out


def assert_same(a: dict, b: dict) -> None:
    assert a.keys() == b.keys()
    for key in a:
        if isinstance(a[key], dict):
            assert a[key] == b[key], f"{key} differs: {a[key]} != {b[key]}"
            continue
        xs, ys = (a[key], b[key]) if isinstance(a[key], list) else ([a[key]], [b[key]])
        assert len(xs) == len(ys), key
        for x, y in zip(xs, ys):
            assert np.array_equal(x, y), f"{key} differs: max |diff| {np.abs(np.asarray(x) - np.asarray(y)).max()}"


@pytest.fixture(scope="module")
def first(tmp_path_factory):
    root = tmp_path_factory.mktemp("repro") / "first"
    runner.run("synthetic", until=[UNTIL, "reference"], overrides=REPRO, artifacts=root)
    return {**outputs(root), "content": content(root)}


def content(root) -> dict:
    """The content digest of each stage's version: equal bytes, equal digests, so later stages reuse."""
    store = runner.Store(root, "synthetic")
    return {stage: store.content(stage, store.current(stage)) for stage in ("anchors", UNTIL)}


def test_two_runs_from_an_empty_cache_write_the_same_artifacts(first, tmp_path):
    runner.run("synthetic", until=[UNTIL, "reference"], overrides=REPRO, artifacts=tmp_path / "second")
    assert_same(first, {**outputs(tmp_path / "second"), "content": content(tmp_path / "second")})


def test_interrupted_and_resumed_equals_uninterrupted(first, tmp_path, monkeypatch):
    root = tmp_path / "interrupted"
    runner.run("synthetic", until="anchors", overrides=REPRO, artifacts=root)
    step = Trainer.train_step
    hits = []

    def killed(self, *args, **kwargs):  # a kill between two checkpoints of the last successor round
        if self.checkpoint_path is not None and self.checkpoint_path.name == "round_2.pt" and self.step == 15:
            hits.append(self.step)
            raise KeyboardInterrupt
        return step(self, *args, **kwargs)

    monkeypatch.setattr(Trainer, "train_step", killed)
    with pytest.raises(KeyboardInterrupt):
        runner.run("synthetic", until=[UNTIL, "reference"], overrides=REPRO, artifacts=root)
    assert hits == [15]
    store = runner.Store(root, "synthetic")
    assert store.current(UNTIL) is None  # nothing published
    (ckpt_dir,) = store.stage_dir(UNTIL).glob(".ckpt-*")
    assert {p.name for p in ckpt_dir.iterdir()} >= {"round_1.pt", "round_2.pt"}

    monkeypatch.setattr(Trainer, "train_step", step)
    runner.run("synthetic", until=[UNTIL, "reference"], overrides=REPRO, artifacts=root)
    log = (version(root, UNTIL) / "log.txt").read_text()
    assert "round 2: resumed from round_2.pt at step 10" in log
    assert_same(first, {**outputs(root), "content": content(root)})  # the same bytes: later stages reuse theirs


def test_sigkill_at_random_moments_then_rerun(first, tmp_path):
    """Fault injection: a subprocess run killed with SIGKILL at seeded random moments; after every
    kill no partial version is visible, and the final rerun's outputs equal an uninterrupted run's."""
    import signal
    import subprocess
    import sys
    import time

    root = tmp_path / "killed"
    cmd = [sys.executable, str(runner.ROOT / "pipeline.py"), "run", "--scene", "synthetic", "--until", "anchors",
           "--artifacts", str(root), *sum((["--set", s] for s in REPRO), [])]
    rng = np.random.default_rng(11)
    store = runner.Store(root, "synthetic")
    killed = 0
    for delay in rng.uniform(2.0, 10.0, size=3):
        proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        time.sleep(delay)
        proc.send_signal(signal.SIGKILL)
        killed += proc.wait() == -signal.SIGKILL  # else it had finished before the kill
        for stage in runner.load_stages():  # the stages' folders; .locks holds lock files, not versions
            stage_dir = store.stage_dir(stage)
            for entry in stage_dir.iterdir() if stage_dir.is_dir() else ():
                if not entry.name.startswith(".") and not entry.is_symlink():
                    assert store.is_complete(stage_dir.name, entry.name), f"partial version visible: {entry}"
    assert killed >= 1  # a later run resumes the earlier ones and may finish before its kill
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    out = outputs_until_anchors(root)
    assert_same({k: first[k] for k in out}, out)


def outputs_until_anchors(root) -> dict:
    d = version(root, "anchors") / "round_0"
    model = torch.load(d / "model.pt", map_location="cpu", weights_only=False)
    return {"anchors_w2c": readers.load_round(d)["w2c"], "anchors_field": [t.numpy() for t in model["field"].values()],
            "schedule": readers.load_schedule(version(root, "schedule"))["round"]}
