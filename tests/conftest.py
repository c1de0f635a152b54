"""Shared fixtures: small scenes in every layout, built by the tests themselves."""
from __future__ import annotations

import os
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
# As in runner/__init__.py, but before anything imports torch (manifoldneus below does): busy-waiting
# OpenMP threads made the neural tests about 3x slower on a shared 2-core machine.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parent.parent

from manifoldneus.data import io, scenes  # noqa: E402

SHARED_DATA = scenes.default_data_root()
needs_dtu = pytest.mark.skipif(not (SHARED_DATA / "dtu" / "scan24").is_dir(), reason="shared DTU data absent")


# `MANIFOLDNEUS_TEST_DEVICE=cuda make test`: every pipeline run of the suite (unless a test names its own
# run.device) and test_neural's trainers compute the neural stages on that device: the check for a GPU
# machine. CI and the default are the CPU.
TEST_DEVICE = os.environ.get("MANIFOLDNEUS_TEST_DEVICE", "cpu")


@pytest.fixture(autouse=True, scope="session")
def neural_stages_on_test_device():
    if TEST_DEVICE == "cpu":
        yield
        return
    import inspect

    from runner import execute, params
    from runner import inspect as runner_inspect

    resolve = params.resolve_params
    signature = inspect.signature(resolve)

    def on_test_device(*args, **kwargs):
        bound = signature.bind(*args, **kwargs)
        overrides = list(bound.arguments.get("overrides", ()))
        if not any(o.startswith("run.device=") for o in overrides):
            bound.arguments["overrides"] = [*overrides, f"run.device={TEST_DEVICE}"]
        return resolve(*bound.args, **bound.kwargs)

    # runs and `status` alike (a status on params.yaml's cpu would call every neural stage stale); README's
    # figures still compare against params.yaml
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(execute, "resolve_params", on_test_device)
        mp.setattr(runner_inspect, "resolve_params", on_test_device)
        yield


# grid_sample's CUDA backward (the dense grid levels) adds with atomics and has no deterministic version, so
# on cuda one seed gives one result only to float tolerance; the bitwise tests hold on the CPU.
bitwise_on_cpu = pytest.mark.skipif(TEST_DEVICE != "cpu", reason="bitwise reproducibility is a CPU property "
                                    "(grid_sample's CUDA backward is not deterministic)")


# The whole pipeline on a tiny synthetic scene (CPU, about two minutes on a loaded 2-core machine).
TINY = [
    "ingest.synthetic_views=20", "ingest.synthetic_resolution=128", "ingest.synthetic_surface_points=4000",
    "reference_surface.iters=40", "train.image_size=32", "train.batch_rays=256", "train.warmup=5", "train.log_every=10",
    "anchors.iters=40", "successors.iters=30", "successors.final_iters=40", "surface.iters=40",
    "field.grid_levels=3", "field.grid_max_res=32", "render.cache_res=32",
    "meshing.resolution=48", "evaluate.chamfer_points=4000", "schedule.successors_per_round=4",
    "novel_views.align_steps=10", "novel_views.align_rays=256",
    "successors.polish_steps=20", "successors.polish_rays=256",
    "run.threads=1",  # `make test` runs two workers on two cores: two torch threads each would oversubscribe them
]
# TINY's successors placed in one round, not three: for the tests that read nothing of the rounds
ONE_SUCCESSOR_ROUND = "schedule.successors_per_round=20"


# The longest test files (by a whole run's durations, 2026-11-29), run first: `make test` hands whole files
# to its two workers in collection order (--no-loadscope-reorder), and a long file handed out last keeps one
# core busy after the other has finished. The two longest build no shared fixture, so neither worker starts
# by waiting for the other's `tiny_build`.
LONGEST_FIRST = ("test_self_calibration.py", "test_bench.py", "test_end_to_end.py", "test_sweep.py",
                 "test_reproducible.py", "test_pipeline.py", "test_object_region.py", "test_bench_refine.py",
                 "test_neural.py", "test_pose_init.py", "test_bench_own_photos.py", "test_executor.py",
                 "test_install.py", "test_ingest.py", "test_viewer.py", "test_report.py",
                 "test_frontend_matching.py", "test_gpu_step.py")


def pytest_collection_modifyitems(config, items):
    rank = {name: i for i, name in enumerate(LONGEST_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))  # stable: the order inside a file stays


@pytest.fixture(scope="session")
def tiny_build(tmp_path_factory):
    """(artifacts folder, run report) of one TINY run, built once per pytest run: the first worker to ask
    builds it, another waits for it. Never written to: tests take copies (tiny_run, tiny_copy)."""
    import json

    import filelock

    import runner

    base = tmp_path_factory.getbasetemp()
    # under xdist each worker's base folder lies in the pytest run's own: build there, once for all of them
    shared = (base.parent if "PYTEST_XDIST_WORKER" in os.environ else base) / "tiny_run"
    shared.mkdir(exist_ok=True)
    with filelock.FileLock(str(shared) + ".lock"):
        if not (shared / "report.json").is_file():
            built = runner.run("synthetic", overrides=TINY, artifacts=shared / "artifacts")
            (shared / "report.json").write_text(json.dumps({"stages": built, "fingerprints": built.fingerprints}))
    saved = json.loads((shared / "report.json").read_text())
    report = runner.RunReport()
    report.update(saved["stages"])
    report.fingerprints.update(saved["fingerprints"])
    return shared / "artifacts", report


def copy_of(artifacts: Path, to: Path) -> Path:
    import shutil

    shutil.copytree(artifacts, to, symlinks=True)  # the `current` pointers are relative links
    return to


@pytest.fixture(scope="session")
def tiny_run(tiny_build, tmp_path_factory):
    """(artifacts folder, run report) of the TINY run, this worker's copy, shared by the test modules. Tests
    that run other parameters into it move some stages' `current` pointers: read a result through
    `Store.lineage` of its last stage, which names the versions it was computed from."""
    return copy_of(tiny_build[0], tmp_path_factory.mktemp("e2e") / "artifacts"), tiny_build[1]


@pytest.fixture
def tiny_copy(tiny_build, tmp_path):
    """An artifacts folder of the test's own holding every stage of the TINY run: a run of TINY's parameters
    into it reuses them."""
    return copy_of(tiny_build[0], tmp_path / "tiny_artifacts")


@pytest.fixture(scope="session")
def tiny_synthetic():
    from manifoldneus.data import synthetic

    return synthetic.make_scene(seed=1, n_views=6, resolution=64)


@pytest.fixture
def idr_folder(tmp_path, tiny_synthetic):
    """An IDR/NeuS layout of the tiny synthetic scene (world = normalised frame, scale_mat = I)."""
    s = tiny_synthetic
    root = tmp_path / "idr_scene"
    (root / "image").mkdir(parents=True)
    (root / "mask").mkdir()
    cams = {}
    for i in range(len(s.images)):
        io.save_png(root / "image" / f"{i:03d}.png", s.images[i])
        io.save_png(root / "mask" / f"{i:03d}.png", np.repeat(s.masks[i][..., None], 3, -1).astype(np.uint8) * 255)
        P = np.eye(4)
        P[:3, :4] = s.K[i] @ s.w2c[i][:3, :4]
        cams[f"world_mat_{i}"] = P
        cams[f"scale_mat_{i}"] = np.eye(4)
    np.savez(root / "cameras_sphere.npz", **cams)
    return root


@pytest.fixture
def colmap_folder(tmp_path, tiny_synthetic):
    """A COLMAP text model (PINHOLE cameras, no points) beside images/."""
    import roma
    import torch

    s = tiny_synthetic
    root = tmp_path / "colmap_scene"
    (root / "images").mkdir(parents=True)
    (root / "sparse" / "0").mkdir(parents=True)
    K = s.K[0]
    (root / "sparse/0/cameras.txt").write_text(
        f"1 PINHOLE {s.images.shape[2]} {s.images.shape[1]} {K[0, 0]} {K[1, 1]} {K[0, 2]} {K[1, 2]}\n")
    lines = []
    for i in range(len(s.images)):
        io.save_png(root / "images" / f"view{i:02d}.png", s.images[i])
        q = roma.rotmat_to_unitquat(torch.as_tensor(s.w2c[i][:3, :3]))  # xyzw
        x, y, z, w = q.tolist()
        t = s.w2c[i][:3, 3]
        lines.append(f"{i + 1} {w} {x} {y} {z} {t[0]} {t[1]} {t[2]} 1 view{i:02d}.png\n\n")
    (root / "sparse/0/images.txt").write_text("".join(lines))
    (root / "sparse/0/points3D.txt").write_text("")
    return root


@pytest.fixture
def plain_folder(tmp_path, tiny_synthetic):
    root = tmp_path / "photos"
    root.mkdir()
    for i, im in enumerate(tiny_synthetic.images):
        io.save_png(root / f"IMG_{i:04d}.png", im)
    return root


@pytest.fixture
def artifacts(tmp_path):
    return tmp_path / "artifacts"
