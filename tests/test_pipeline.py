"""The DAG runner: caching, invalidation, atomic writes, locking, params validation, CLI errors."""
from __future__ import annotations

import json
import shutil

import pytest

import manifoldneus
import pipeline
import runner
import runner.common
import runner.fingerprint
import runner.store
from manifoldneus.config import ParamError
from manifoldneus.data.scenes import SceneError
from tests.conftest import TINY, needs_dtu

FAST_SYNTH = ["ingest.synthetic_views=6", "ingest.synthetic_resolution=64", "ingest.synthetic_surface_points=2000"]


def test_rerun_reuses_and_param_roundtrip_does_not_recompute(artifacts):
    first = runner.run("synthetic", until="ground_truth", overrides=FAST_SYNTH, artifacts=artifacts)
    assert first == {"ingest": "computed", "ground_truth": "computed"}
    again = runner.run("synthetic", until="ground_truth", overrides=FAST_SYNTH, artifacts=artifacts)
    assert again == {"ingest": "reused", "ground_truth": "reused"}

    changed = FAST_SYNTH + ["ingest.load_masks=false"]
    st = runner.status("synthetic", overrides=changed, artifacts=artifacts)
    assert st["ingest"][0] == "stale"
    assert any("ingest.load_masks" in r for r in st["ingest"][1])
    assert st["ground_truth"][0] == "stale"  # same section, and its upstream changed
    assert runner.run("synthetic", until="ingest", overrides=changed, artifacts=artifacts)["ingest"] == "computed"

    # setting it back: the earlier version is current again without recomputation
    st = runner.status("synthetic", overrides=FAST_SYNTH, artifacts=artifacts)
    assert st["ingest"][0] == "stale" and any("will be reused" in r for r in st["ingest"][1])
    assert runner.run("synthetic", until="ingest", overrides=FAST_SYNTH, artifacts=artifacts) == {"ingest": "reused"}
    assert runner.status("synthetic", overrides=FAST_SYNTH, artifacts=artifacts)["ingest"] == ("fresh", [])


@needs_dtu
def test_scan24_ingest_fresh_stale_fresh(artifacts):
    assert runner.run("scan24", until="ingest", artifacts=artifacts) == {"ingest": "computed"}
    assert runner.status("scan24", artifacts=artifacts)["ingest"] == ("fresh", [])
    st = runner.status("scan24", overrides=["ingest.downscale=2"], artifacts=artifacts)
    assert st["ingest"][0] == "stale"
    assert runner.run("scan24", until="ingest", overrides=["ingest.downscale=2"], artifacts=artifacts) == {
        "ingest": "computed"}
    assert runner.run("scan24", until="ingest", artifacts=artifacts) == {"ingest": "reused"}
    assert runner.status("scan24", artifacts=artifacts)["ingest"] == ("fresh", [])


def test_failure_mid_write_publishes_nothing_and_rerun_succeeds(artifacts, monkeypatch):
    import stages.ingest as ingest

    real_run = ingest.run

    def crashing_run(ctx):
        (ctx.out / "views.json").write_text("{half")  # something half-written
        raise KeyboardInterrupt("killed mid-write")

    monkeypatch.setattr(ingest, "run", crashing_run)
    with pytest.raises(KeyboardInterrupt):
        runner.run("synthetic", until="ingest", overrides=FAST_SYNTH, artifacts=artifacts)
    store = runner.Store(artifacts, "synthetic")
    assert store.current("ingest") is None
    versions = [p for p in store.stage_dir("ingest").iterdir() if not p.name.startswith(".")]
    assert versions == []  # only a .failed-* folder with the log, never a fingerprint folder
    assert runner.status("synthetic", overrides=FAST_SYNTH, artifacts=artifacts)["ingest"][0] == "missing"

    monkeypatch.setattr(ingest, "run", real_run)
    assert runner.run("synthetic", until="ingest", overrides=FAST_SYNTH, artifacts=artifacts) == {
        "ingest": "computed"}
    manifest = store.manifest("ingest")
    assert manifest["metrics"]["n_views"] == 6 and manifest["peak_rss_mib"] > 0


def test_gc_refuses_while_a_run_is_in_progress(artifacts):
    runner.run("synthetic", until="ingest", overrides=FAST_SYNTH, artifacts=artifacts)
    store = runner.Store(artifacts, "synthetic")
    with store.in_use():  # as a run in another process holds it
        with pytest.raises(runner.PipelineError, match="a run on .* is in progress"):
            runner.gc(artifacts, "synthetic")
        # runs of one scene go side by side: each version has its own lock
        assert runner.run("synthetic", until="ingest", overrides=FAST_SYNTH + ["ingest.downscale=2"],
                            artifacts=artifacts) == {"ingest": "computed"}


def test_truncated_manifest_is_a_missing_version(artifacts):
    runner.run("synthetic", until="ingest", overrides=FAST_SYNTH, artifacts=artifacts)
    store = runner.Store(artifacts, "synthetic")
    manifest = store.version_dir("ingest", store.current("ingest")) / "manifest.json"
    manifest.write_text(manifest.read_text()[:40])
    assert runner.status("synthetic", overrides=FAST_SYNTH, artifacts=artifacts)["ingest"][0] == "missing"
    assert runner.run("synthetic", until="ingest", overrides=FAST_SYNTH, artifacts=artifacts) == {"ingest": "computed"}
    assert json.loads(manifest.read_text())["stage"] == "ingest"


def test_force_recomputes(artifacts):
    runner.run("synthetic", until="ingest", overrides=FAST_SYNTH, artifacts=artifacts)
    out = runner.run("synthetic", until="ingest", overrides=FAST_SYNTH, force=["ingest"], artifacts=artifacts)
    assert out == {"ingest": "computed"}


def test_code_change_makes_stage_stale(artifacts, monkeypatch):
    runner.run("synthetic", until="ingest", overrides=FAST_SYNTH, artifacts=artifacts)
    monkeypatch.setattr(runner.fingerprint, "code_hash", lambda stage: "edited")
    st = runner.status("synthetic", overrides=FAST_SYNTH, artifacts=artifacts)
    assert st["ingest"][0] == "stale" and any("code" in r for r in st["ingest"][1])


def test_code_hash_covers_package_modules():
    stages = runner.load_stages()
    files = {p.relative_to(runner.ROOT).as_posix() for p in runner.fingerprint._code_files(stages["ingest"].module)}
    assert {"stages/ingest.py", "manifoldneus/data/scenes.py", "manifoldneus/data/io.py", "manifoldneus/config.py",
            "manifoldneus/geometry/cameras.py"} <= files
    # imported only inside functions (scenes.py, evaluate.py): still the stages' code
    assert "manifoldneus/data/synthetic.py" in files
    evaluate = {p.name for p in runner.fingerprint._code_files(stages["evaluate"].module)}
    assert "synthetic.py" in evaluate
    # ...but not modules the stage never reaches, nor the stage registry
    assert "train.py" not in files and "stages/__init__.py" not in files
    # the C++ a reached module compiles at run time is part of the stage's code
    anchors = {p.relative_to(runner.ROOT).as_posix() for p in runner.fingerprint._code_files(stages["anchors"].module)}
    assert "manifoldneus/neural/csrc/grid_encoding.cpp" in anchors and "manifoldneus/neural/csrc/grid_encoding.cpp" not in files
    # the front end writes and reads through manifoldneus.data.artifacts, which must not reach the trainer
    covisibility = {p.name for p in runner.fingerprint._code_files(stages["covisibility"].module)}
    assert "artifacts.py" in covisibility and "train.py" not in covisibility


def test_editing_a_lazily_imported_module_makes_the_stage_stale(artifacts, tmp_path, monkeypatch):
    """scenes.py imports synthetic.py inside a function: an edit there must reach ingest's fingerprint."""
    copy = tmp_path / "src"
    for folder in ("manifoldneus", "stages"):
        shutil.copytree(runner.ROOT / folder, copy / folder, ignore=shutil.ignore_patterns("__pycache__"))
    monkeypatch.setattr(runner.common, "ROOT", copy)
    runner.run("synthetic", until="ingest", overrides=FAST_SYNTH, artifacts=artifacts)
    assert runner.status("synthetic", overrides=FAST_SYNTH, artifacts=artifacts)["ingest"][0] == "fresh"

    generator = copy / "manifoldneus" / "data" / "synthetic.py"
    generator.write_text(generator.read_text() + "\n# an edit to the scene generator\n")
    st = runner.status("synthetic", overrides=FAST_SYNTH, artifacts=artifacts)
    assert st["ingest"][0] == "stale" and any("code" in r for r in st["ingest"][1])


@pytest.mark.parametrize(
    "override, message",
    [
        ("ingest.nonsense=1", "unknown parameter ingest.nonsense"),
        ("ingest.downscale=0", "ingest.downscale: 0 is below the minimum 1"),
        ("ingest.downscale=abc", "ingest.downscale: expected an integer"),
        ("ingest.layout=zip", "ingest.layout: 'zip' is not one of"),
        ("nosection.key=1", "unknown section 'nosection'"),
        ("downscale=2", "expected section.key=value"),
        ("ingest.load_masks=maybe", "ingest.load_masks: expected true/false"),
        ("matching.ratio=.nan", "matching.ratio: expected a finite number"),
        ("schedule.alpha=nan", "schedule.alpha: expected a finite number"),
        ("ingest.intrinsics=[500,500,nan,192]", "ingest.intrinsics: expected a finite number"),
        ("train.lr=inf", "train.lr: expected a finite number"),
        ("anchors.perturb_rot_deg=[5,3]", r"anchors.perturb_rot_deg: expected \[lo, hi\] with lo <= hi"),
        ("anchors.perturb_rot_deg=[-1,3]", "anchors.perturb_rot_deg: -1.0 is below the minimum 0.0"),
        ("anchors.refine_intrinsics=[focal, skew]", r"anchors.refine_intrinsics: \['skew'\] not among"),
        ("reference.refine_intrinsics=[radial]", r"reference.refine_intrinsics: \['radial'\] not among"),
        ("ingest.intrinsics=[0,500,96,96]", r"ingest.intrinsics: .* positive focal lengths"),
        ("ingest.intrinsics=[500,-500,96,96]", r"ingest.intrinsics: .* positive focal lengths"),
        ("ingest.intrinsics=[500,96,96]", r"ingest.intrinsics: .* is not \[fx, fy, cx, cy\]"),
    ],
)
def test_bad_set_is_a_clear_error(artifacts, override, message):
    with pytest.raises(ParamError, match=message):
        runner.run("synthetic", until="ingest", overrides=[override], artifacts=artifacts)


def test_an_unavailable_device_stops_the_run_before_its_first_stage(artifacts, monkeypatch):
    import torch

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)  # as on this CPU machine
    with pytest.raises(ParamError, match=r"run.device: 'cuda' is not available on this machine .* use cpu"):
        runner.run("synthetic", until="anchors", overrides=["run.device=cuda"], artifacts=artifacts)
    with pytest.raises(ParamError, match=r"run.device: 'gpu' is not a torch device"):
        runner.run("synthetic", until="anchors", overrides=["run.device=gpu"], artifacts=artifacts)
    assert not artifacts.exists()  # nothing computed, nothing created
    # stages that never touch torch's device do not need it
    assert runner.run("synthetic", until="ingest", overrides=[*FAST_SYNTH, "run.device=cuda"], artifacts=artifacts)


def test_unknown_stage_and_profile(artifacts):
    with pytest.raises(runner.PipelineError, match="unknown stage 'featurez'"):
        runner.run("synthetic", until="featurez", artifacts=artifacts)
    with pytest.raises(ParamError, match="unknown profile"):
        runner.run("synthetic", until="ingest", profile="turbo", artifacts=artifacts)


def test_the_quick_profile_is_fast_with_half_the_surface():
    """params.yaml's profiles resolve; `quick` differs from `fast` in the surface's and the GT-pose
    reference's lengths (halved) and the field (fast's finer hashed finest level needs fast's iterations)
    only: the same rounds, so the same poses; both keep the fitted views' bands between rounds."""
    stages = runner.load_stages()
    fast, quick = (runner.resolve_params(stages, profile=name) for name in ("fast", "quick"))
    runner.resolve_params(stages, profile="paper")
    lengths = [("surface", "iters"), ("reference_surface", "iters")]
    for section, key in lengths:
        assert 2 * getattr(quick[section], key) == getattr(fast[section], key), (section, key)
    assert fast["successors"].regate_kept == quick["successors"].regate_kept == 1.0
    differ = {(name, key) for name in fast if not name.startswith("_")
              for key in vars(fast[name]) if getattr(fast[name], key) != getattr(quick[name], key)}
    assert (fast["field"].grid_max_res, quick["field"].grid_max_res) == (256, 128)
    assert differ == {*lengths, ("field", "grid_max_res"), ("field", "grid_hash_log2")}, differ


def test_unknown_params_yaml_section(tmp_path, artifacts):
    bad = tmp_path / "params.yaml"
    bad.write_text("profile: fast\nprofiles: {fast: {}}\ningestt: {downscale: 2}\n")
    with pytest.raises(ParamError, match="unknown section 'ingestt'"):
        runner.run("synthetic", until="ingest", params_path=bad, artifacts=artifacts)


def test_cli_reports_errors_without_traceback(capsys, artifacts):
    code = pipeline.main(["run", "--scene", "synthetic", "--until", "nope", "--artifacts", str(artifacts)])
    assert code == 2 and "unknown stage 'nope'" in capsys.readouterr().err
    code = pipeline.main(["run", "--scene", "synthetic", "--set", "ingest.downscale=-3", "--artifacts", str(artifacts)])
    assert code == 2 and "below the minimum" in capsys.readouterr().err


def test_a_multi_scene_run_as_a_script_reports_a_bad_stage_in_one_line(artifacts):
    """Run as a script, pipeline.py is `__main__`: the executor's errors must be the classes the CLI
    catches (it once imported a second copy of the runner and printed `error: PipelineError: ...`)."""
    import subprocess
    import sys

    done = subprocess.run([sys.executable, str(runner.ROOT / "pipeline.py"), "run", "--scene", "synthetic",
                           "--scene", "synthetic-1", "--until", "nope", "--artifacts", str(artifacts)],
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 2, done.stderr
    assert done.stderr.strip().splitlines()[-1].startswith("error: unknown stage 'nope' for --until"), done.stderr


def test_cli_status_show_params_diff_gc(capsys, artifacts):
    args = ["--scene", "synthetic", "--artifacts", str(artifacts)]
    sets = sum((["--set", s] for s in FAST_SYNTH), [])
    assert pipeline.main(["run", *args, *sets, "--until", "ground_truth"]) == 0
    assert pipeline.main(["show", *args, "ingest"]) == 0
    out = capsys.readouterr().out
    assert "views.zarr/" in out and "images" in out and "n_views = 6" in out
    assert pipeline.main(["params-diff", *args, *sets, "--set", "ingest.downscale=2", "ingest"]) == 0
    assert "ingest.downscale: 1 -> 2" in capsys.readouterr().out
    assert pipeline.main(["run", *args, *sets, "--set", "ingest.downscale=2", "--until", "ingest"]) == 0
    report = artifacts / "synthetic" / "report" / "figs"  # a non-stage folder gc must leave alone
    report.mkdir(parents=True)
    # ground_truth's current version was computed from the first ingest: that one stays
    assert pipeline.main(["gc", "--artifacts", str(artifacts)]) == 0
    assert "removed 0 old version" in capsys.readouterr().out
    assert pipeline.main(["run", *args, *sets, "--set", "ingest.downscale=2", "--until", "ground_truth"]) == 0
    assert pipeline.main(["gc", "--artifacts", str(artifacts)]) == 0
    assert "removed 2 old version" in capsys.readouterr().out
    assert report.is_dir()


def test_a_reader_that_goes_away_ends_the_command_quietly(capsys, tmp_path, monkeypatch):
    """`status ... | head -3`: the pipe closes under the printing; the command stops with the shell's
    SIGPIPE status (141) and no `error:` line."""
    import sys

    class ClosedPipe:
        def __init__(self):
            self.sink = open(tmp_path / "sink", "w")

        def write(self, text):
            raise BrokenPipeError(32, "Broken pipe")

        def flush(self):
            pass

        def fileno(self):
            return self.sink.fileno()

    monkeypatch.setattr(sys, "stdout", ClosedPipe())
    assert pipeline.main(["status", "--scene", "synthetic", "--artifacts", str(tmp_path / "art")]) == 141
    assert "error" not in capsys.readouterr().err


@pytest.mark.parametrize("command", ["run", "status", "gc", "verify"])
def test_artifacts_naming_a_file_is_one_error_line(command, capsys, tmp_path):
    (tmp_path / "a-file").write_text("not a folder")
    scene = [] if command == "gc" else ["--scene", "synthetic"]
    assert pipeline.main([command, *scene, "--artifacts", str(tmp_path / "a-file")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: --artifacts") and "is a file, not a folder" in err


def test_gc_acts_only_on_versions_it_wrote_inside_the_artifacts_root(capsys, tmp_path, monkeypatch):
    artifacts = tmp_path / "work" / "artifacts"
    sets = sum((["--set", s] for s in FAST_SYNTH), [])
    assert pipeline.main(["run", "--scene", "synthetic", "--artifacts", str(artifacts), *sets, "--until", "ingest"]) == 0
    # a user's photo folder with subfolders named like stages, and stage-named folders beside the artifacts
    photos = tmp_path / "photos"
    user_files = []
    for where in (photos / "mesh" / "keep", photos / "export" / "keep", tmp_path / "work" / "mesh" / "keep",
                  artifacts / "synthetic" / "ingest" / "notes"):  # the last: not a version of ours
        where.mkdir(parents=True)
        (where / "mine.txt").write_text("a user's file")
        user_files.append(where / "mine.txt")
    (artifacts / "synthetic" / "ingest" / "0123456789ab").mkdir()  # a fingerprint-like name, no manifest of ours
    monkeypatch.chdir(artifacts)
    before = sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*"))
    for scene in (str(photos), "..", str(tmp_path / "work")):
        assert pipeline.main(["gc", "--scene", scene, "--artifacts", str(artifacts)]) == 2
        assert "no artifacts of scene" in capsys.readouterr().err
    assert pipeline.main(["gc", "--scene", "no-such-scene", "--artifacts", str(artifacts)]) == 2
    assert "not found" in capsys.readouterr().err
    assert pipeline.main(["gc", "--scene", "synthetic", "--artifacts", str(tmp_path / "nowhere")]) == 2
    assert not (tmp_path / "nowhere").exists()
    assert sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*")) == before  # nothing removed, nothing created

    # an old version of ours: listed by --dry-run, removed by gc; the user's files stay
    assert pipeline.main(["run", "--scene", "synthetic", "--artifacts", str(artifacts), *sets,
                          "--set", "ingest.downscale=2", "--until", "ingest"]) == 0
    capsys.readouterr()
    assert pipeline.main(["gc", "--artifacts", str(artifacts), "--dry-run"]) == 0
    out = capsys.readouterr().out
    assert "would remove 1 old version(s)" in out and "MiB" in out
    old = [p for p in (artifacts / "synthetic" / "ingest").iterdir() if runner.store._our_version(p.parent, p)
           and p.name != runner.Store(artifacts, "synthetic").current("ingest")]
    assert len(old) == 1 and old[0].is_dir()
    assert pipeline.main(["gc", "--scene", "synthetic", "--artifacts", str(artifacts)]) == 0
    assert f"removed {old[0]}" in capsys.readouterr().out and not old[0].exists()
    assert all(f.read_text() == "a user's file" for f in user_files)
    assert (artifacts / "synthetic" / "ingest" / "0123456789ab").is_dir()
    assert runner.Store(artifacts, "synthetic").current("ingest") is not None


def test_gc_drops_leftovers_of_ended_runs_only(artifacts):
    import os
    import socket
    import subprocess

    runner.run("synthetic", until="ingest", overrides=FAST_SYNTH, artifacts=artifacts)
    store = runner.Store(artifacts, "synthetic")
    fp = store.current("ingest")
    dead = subprocess.Popen(["true"])
    dead.wait()
    host = socket.gethostname()
    names = {"dead": f".tmp-{fp}-{host}-{dead.pid}", "alive": f".tmp-{fp}-{host}-{os.getpid()}",
             "published": f".ckpt-{fp}", "resumable": ".ckpt-0123456789ab", "orphaned": ".ckpt-ba9876543210"}
    for name in names.values():
        (store.stage_dir("ingest") / name).mkdir()
        (store.stage_dir("ingest") / name / "state.pt").write_bytes(b"x" * 100)
    # the record a killed run left: it was computing ingest 0123456789ab
    (store.scene_dir / ".runs").mkdir(exist_ok=True)
    (store.scene_dir / ".runs" / f"{host}-{dead.pid}.json").write_text(
        '{"pointer": "current", "versions": {"ingest": "0123456789ab"}}')
    removed = runner.gc(artifacts, "synthetic")
    assert sorted(p.name for p in removed) == sorted([names["dead"], names["published"], names["orphaned"]])
    assert (store.stage_dir("ingest") / names["alive"]).is_dir()
    assert (store.stage_dir("ingest") / names["resumable"]).is_dir()
    assert store.current("ingest") == fp


def test_gc_keeps_what_a_killed_run_resumes_from(tmp_path):
    """SIGKILL after the front-end: its versions have no pointer yet, but the run's record keeps
    them (and its checkpoint) through gc; --drop-interrupted gives them up."""
    import signal
    import subprocess
    import sys

    artifacts = tmp_path / "artifacts"
    cmd = [sys.executable, str(runner.ROOT / "pipeline.py"), "run", "--scene", "synthetic", "--until", "anchors",
           "--artifacts", str(artifacts), *sum((["--set", s] for s in TINY), [])]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    for line in proc.stderr:
        if line.startswith("[anchors] running"):
            proc.send_signal(signal.SIGKILL)
            break
    proc.wait()
    store = runner.Store(artifacts, "synthetic")
    [(record_path, record)] = store.interrupted_runs()
    finished = {stage: fp for stage, fp in record["versions"].items() if store.is_complete(stage, fp)}
    assert {"ingest", "features", "matching", "schedule"} <= set(finished) and "anchors" not in finished
    assert store.current("schedule") is None  # killed before its pointers moved
    ckpt = store.stage_dir("anchors") / f".ckpt-{record['versions']['anchors']}"
    ckpt.mkdir(parents=True, exist_ok=True)
    orphan = store.stage_dir("anchors") / ".ckpt-ba9876543210"
    orphan.mkdir()
    removed = runner.gc(artifacts, "synthetic")
    assert orphan in removed and ckpt.is_dir() and record_path.is_file()
    assert all(store.is_complete(stage, fp) for stage, fp in finished.items())
    removed = runner.gc(artifacts, "synthetic", drop_interrupted=True)
    assert not any(store.is_complete(stage, fp) for stage, fp in finished.items()) and not ckpt.exists()
    assert record_path in removed and not record_path.exists()


def test_gc_keeps_the_checkpoint_a_ctrl_c_left_to_resume(artifacts, monkeypatch):
    """Ctrl-C in a stage: the run's record stays (its process then ends), so gc keeps the checkpoint
    the same command resumes from."""
    import socket
    import subprocess

    import stages.features as features

    def interrupted(ctx):
        ctx.checkpoint_dir.mkdir(parents=True, exist_ok=True)
        (ctx.checkpoint_dir / "state.pt").write_bytes(b"x")
        raise KeyboardInterrupt

    monkeypatch.setattr(features, "run", interrupted)
    with pytest.raises(KeyboardInterrupt):
        runner.run("synthetic", until="features", overrides=FAST_SYNTH, artifacts=artifacts)
    monkeypatch.undo()
    store = runner.Store(artifacts, "synthetic")
    [record] = (store.scene_dir / ".runs").glob("*.json")
    dead = subprocess.Popen(["true"])
    dead.wait()
    record.rename(record.with_name(f"{socket.gethostname()}-{dead.pid}.json"))  # as when the process has ended
    [ckpt] = store.stage_dir("features").glob(".ckpt-*")
    runner.gc(artifacts, "synthetic")
    assert ckpt.is_dir() and store.current("ingest") is not None


def test_a_run_that_ends_leaves_no_record(artifacts):
    runner.run("synthetic", until="ingest", overrides=FAST_SYNTH, artifacts=artifacts)
    assert not list((artifacts / "synthetic" / ".runs").glob("*.json"))


def test_sigterm_ends_a_run_as_ctrl_c_does(tmp_path):
    import signal
    import subprocess
    import sys

    artifacts = tmp_path / "artifacts"
    cmd = [sys.executable, str(runner.ROOT / "pipeline.py"), "run", "--scene", "synthetic", "--until", "reference",
           "--artifacts", str(artifacts), *sum((["--set", s] for s in TINY), [])]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    seen = []
    for line in proc.stderr:  # terminate it inside COLMAP's stage (pycolmap has a signal handler of its own)
        seen.append(line)
        if line.startswith("[reference] running"):
            proc.send_signal(signal.SIGTERM)
            break
    rest = proc.stderr.read()
    assert proc.wait() == 143, "".join(seen) + rest
    assert "terminated (SIGTERM): nothing half-written was published" in rest
    assert "Traceback" not in rest and "***" not in rest and len(rest.strip().splitlines()) <= 2, rest
    store = runner.Store(artifacts, "synthetic")
    for stage in runner.load_stages():
        stage_dir = store.stage_dir(stage)
        for entry in stage_dir.iterdir() if stage_dir.is_dir() else ():
            assert not entry.name.startswith(".tmp-"), f"left behind: {entry}"
            if not entry.name.startswith(".") and not entry.is_symlink():
                assert store.is_complete(stage, entry.name), f"partial version visible: {entry}"


def test_ctrl_c_while_a_version_folder_is_being_set_up_leaves_no_temporary_folder(artifacts, monkeypatch):
    """The signal of the test above can land between creating a stage's temporary folder and the
    `try` that moves it aside; it is held until the folder is set up, then acts as anywhere else."""
    import os
    import signal

    import runner.execute

    real = runner.execute._stage_logger

    def interrupted_while_setting_up(stage, path):
        os.kill(os.getpid(), signal.SIGINT)  # arrives at the worst moment: the folder exists, no `try` yet
        return real(stage, path)

    monkeypatch.setattr(runner.execute, "_stage_logger", interrupted_while_setting_up)
    # Python's own Ctrl-C handler, as a command line has it (an earlier test in this worker may have set another)
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        with pytest.raises(KeyboardInterrupt):
            runner.run("synthetic", until="ingest", overrides=FAST_SYNTH, artifacts=artifacts)
    finally:
        signal.signal(signal.SIGINT, previous)
    names = [p.name for p in runner.Store(artifacts, "synthetic").stage_dir("ingest").iterdir()]
    assert not [n for n in names if n.startswith(".tmp-")] and any(n.startswith(".failed-") for n in names), names


def test_a_damaged_version_is_named_and_never_read(capsys, artifacts):
    runner.run("synthetic", until="ground_truth", overrides=FAST_SYNTH, artifacts=artifacts)
    store = runner.Store(artifacts, "synthetic")
    version = store.version_dir("ingest", store.current("ingest"))
    chunks = sorted((p for p in (version / "views.zarr").rglob("*") if p.is_file()), key=lambda p: p.stat().st_size)
    chunks[-1].unlink()  # the largest chunk (image data): zarr would read it back as zeros
    state, reasons = runner.status("synthetic", overrides=FAST_SYNTH, artifacts=artifacts)["ingest"]
    assert state == "damaged" and f"{chunks[-1]}: missing" in reasons
    with pytest.raises(runner.PipelineError, match=r"ingest version \w+ is damaged \(.*: missing\); rebuild it: "
                                                     r"python pipeline.py run --scene synthetic --artifacts \S+ "
                                                     r"(--set \S+ )+--until ingest --force ingest"):
        runner.run("synthetic", until="ground_truth", overrides=FAST_SYNTH, artifacts=artifacts)
    with pytest.raises(runner.PipelineError, match="ingest version .* is damaged"):  # read as another's upstream
        runner.run("synthetic", only="ground_truth", overrides=FAST_SYNTH, artifacts=artifacts)
    args = ["--scene", "synthetic", "--artifacts", str(artifacts)]
    assert pipeline.main(["verify", *args]) == 1
    out = capsys.readouterr().out
    assert "ingest             DAMAGED" in out and "ground_truth       ok" in out and "--force ingest" in out

    sets = sum((["--set", s] for s in FAST_SYNTH), [])
    assert pipeline.main(["run", *args, *sets, "--until", "ground_truth", "--force", "ingest"]) == 0
    assert pipeline.main(["verify", *args]) == 0
    # a corruption that keeps the size: only the hashes of `verify` see it
    victim = chunks[0] if chunks[0].exists() else next(p for p in (version / "views.zarr").rglob("*") if p.is_file())
    data = bytearray(victim.read_bytes())
    data[0] ^= 0xFF
    victim.write_bytes(bytes(data))
    assert runner.status("synthetic", overrides=FAST_SYNTH, artifacts=artifacts)["ingest"][0] == "fresh"
    assert pipeline.main(["verify", *args]) == 1
    assert "content differs from its hash" in capsys.readouterr().out
    # a stage computed again re-hashes what it reads: it never caches a result of the damaged bytes
    with pytest.raises(runner.PipelineError, match="ingest version .* is damaged .*content differs"):
        runner.run("synthetic", until="ground_truth", force=["ground_truth"], overrides=FAST_SYNTH, artifacts=artifacts)
    # a manifest cut short: the version is named, not left out
    assert pipeline.main(["run", *args, *sets, "--until", "ground_truth", "--force", "ingest"]) == 0
    manifest = store.version_dir("ground_truth", store.current("ground_truth")) / "manifest.json"
    manifest.write_text(manifest.read_text()[:200])
    assert pipeline.main(["verify", *args]) == 1
    out = capsys.readouterr().out
    assert "ground_truth       DAMAGED" in out and "--force ground_truth" in out and "ingest             ok" in out


def test_upstream_recomputed_to_the_same_bytes_leaves_downstream_fresh(artifacts, tmp_path, monkeypatch):
    """Content cutoff: a comment-only edit of ingest recomputes ingest, and features, whose input
    bytes did not change, is reused."""
    copy = tmp_path / "src"
    for folder in ("manifoldneus", "stages"):
        shutil.copytree(runner.ROOT / folder, copy / folder, ignore=shutil.ignore_patterns("__pycache__"))
    monkeypatch.setattr(runner.common, "ROOT", copy)
    runner.run("synthetic", until="features", overrides=FAST_SYNTH, artifacts=artifacts)
    stage = copy / "stages" / "ingest.py"
    stage.write_text(stage.read_text() + "\n# a comment-only edit\n")
    st = runner.status("synthetic", overrides=FAST_SYNTH, artifacts=artifacts)
    assert st["ingest"][0] == "stale"
    assert st["features"] == ("stale", ["upstream ingest is not computed with these parameters"])
    report = runner.run("synthetic", until="features", overrides=FAST_SYNTH, artifacts=artifacts)
    assert report == {"ingest": "computed", "features": "reused"}
    assert runner.status("synthetic", overrides=FAST_SYNTH, artifacts=artifacts)["features"] == ("fresh", [])
    # different bytes do reach it
    report = runner.run("synthetic", until="features", overrides=[*FAST_SYNTH, "ingest.synthetic_views=7"],
                          artifacts=artifacts)
    assert report == {"ingest": "computed", "features": "computed"}


def test_until_brings_up_only_the_stages_it_depends_on():
    """`--until S` is S's upstream closure, not the prefix of the stage list: anchors does not
    train the GT-pose NeuS or score pycolmap; pycolmap's scoring does not run the front-end."""
    stages = runner.load_stages()
    anchors = runner.select(stages, "anchors", None)
    assert anchors == ["ingest", "features", "matching", "covisibility", "spectral", "schedule", "reference", "anchors"]
    assert runner.select(stages, "evaluate_poses", None) == ["ingest", "ground_truth", "reference", "evaluate_poses"]
    assert runner.select(stages, None, None) == list(stages)  # the whole DAG, in order
    # several stages: the union of their closures (a bench scores pycolmap and the rounds in one run)
    both = runner.select(stages, ["evaluate", "evaluate_poses"], None)
    assert set(both) == set(runner.select(stages, "evaluate", None)) | {"ground_truth", "evaluate_poses"}
    for name in stages:  # every selection is closed under upstream and in DAG order
        chosen = runner.select(stages, name, None)
        assert chosen[-1] == name and all(up in chosen[:chosen.index(n)] for n in chosen for up in stages[n].upstream)


def test_ground_truth_is_structurally_private(monkeypatch):
    import types

    import stages as registry

    sneaky = types.ModuleType("stages.sneaky")
    sneaky.UPSTREAM, sneaky.SECTIONS, sneaky.OUTPUTS = ("ground_truth",), ("ingest",), ()
    sneaky.Params = object
    monkeypatch.setitem(__import__("sys").modules, "stages.sneaky", sneaky)
    monkeypatch.setattr(registry, "STAGES", ["ingest", "ground_truth", "sneaky"])
    with pytest.raises(runner.PipelineError, match="may not read ground truth"):
        runner.load_stages()


def test_context_refuses_undeclared_inputs(artifacts):
    stages = runner.load_stages()
    resolved = runner.resolve_params(stages)
    ctx = runner.Context(stages["ingest"], resolved, runner.Store(artifacts, "x"), {}, artifacts, 
                           runner.resolve_scene("synthetic"), None)
    with pytest.raises(runner.PipelineError, match="declared upstream"):
        ctx.input("ground_truth")


def test_the_anchors_read_pycolmaps_sfm_only_when_they_start_from_it(artifacts):
    """`reference` is an upstream of `anchors` only with anchors.pose_init = reference: otherwise neither
    its version nor its parameters enter the anchors' fingerprint, and `--until anchors` does not run it."""
    stages = runner.load_stages()
    scene = runner.resolve_scene("synthetic")

    def anchors_fingerprint(*over):
        resolved = runner.resolve_params(stages, overrides=[*FAST_SYNTH, *over])
        return runner.compute_fingerprints(runner.for_params(stages, resolved), resolved, scene)["anchors"]

    plain = anchors_fingerprint()
    assert "reference" not in plain["upstream"]
    assert anchors_fingerprint("reference.num_threads=2")["fingerprint"] == plain["fingerprint"]
    from_reference = anchors_fingerprint("anchors.pose_init=reference")
    assert "reference" in from_reference["upstream"]
    assert anchors_fingerprint("anchors.pose_init=reference", "reference.num_threads=2")["fingerprint"] != \
        from_reference["fingerprint"]
    assert "reference" in runner.status("synthetic", overrides=FAST_SYNTH, artifacts=artifacts)  # still a stage
    selected = runner.select(runner.for_params(stages, runner.resolve_params(stages, overrides=FAST_SYNTH)),
                               "anchors", None)
    assert "reference" not in selected and "schedule" in selected


def test_missing_scene_and_data_root_say_where_they_looked(tmp_path):
    with pytest.raises(SceneError, match="does not exist.*synthetic"):
        runner.resolve_scene("scan24", data_root=tmp_path / "nowhere")
    with pytest.raises(SceneError, match="looked in:.*dtu/scan99"):
        runner.resolve_scene("scan99", data_root=tmp_path)


def test_manifest_records_params_versions_and_timing(artifacts):
    runner.run("synthetic", until="ingest", overrides=FAST_SYNTH, artifacts=artifacts)
    path = runner.Store(artifacts, "synthetic").version_dir("ingest", runner.Store(artifacts, "synthetic").current("ingest"))
    m = json.loads((path / "manifest.json").read_text())
    assert m["params"]["ingest"]["synthetic_views"] == 6
    assert {"numpy", "zarr"} <= set(m["libraries"])
    assert m["wall_seconds"] >= 0 and (path / "log.txt").read_text().strip()


def test_presets_keep_their_own_current_pointers(tmp_path, artifacts):
    params = tmp_path / "params.yaml"
    params.write_text("profile: fast\nprofiles: {fast: {}}\npresets: {small: {ingest: {downscale: 2}}}\n")
    kw = dict(overrides=FAST_SYNTH, artifacts=artifacts, params_path=params, until="ingest")
    assert runner.run("synthetic", **kw) == {"ingest": "computed"}
    assert runner.run("synthetic", preset="small", **kw) == {"ingest": "computed"}
    default = runner.Store(artifacts, "synthetic").current("ingest")
    small = runner.Store(artifacts, "synthetic", "small").current("ingest")
    assert default != small  # the preset did not move the default run's pointer
    assert runner.status("synthetic", **{k: v for k, v in kw.items() if k != "until"})["ingest"][0] == "fresh"
    with pytest.raises(ParamError, match="unknown preset 'big'"):
        runner.run("synthetic", preset="big", **kw)


def test_exponent_floats_without_a_dot_are_numbers():
    stages = runner.load_stages()
    resolved = runner.resolve_params(stages, overrides=["anchors.pose_lr=5e-4"])
    assert resolved["anchors"].pose_lr == 5e-4
    # and on/off, which YAML reads as booleans, are the words of a choice
    for word in ("on", "off"):
        assert runner.resolve_params(stages, overrides=[f"meshing.crop_to_object={word}"])["meshing"].crop_to_object == word
    with pytest.raises(ParamError, match="anchors.pose_lr: expected a number"):
        runner.resolve_params(stages, overrides=["anchors.pose_lr=fast"])


def test_imports_point_one_way():
    """pipeline.py (the CLI) -> runner -> stages -> manifoldneus, never back up: no file of a layer
    imports a layer above it (anywhere in the file, function bodies included), so no chain of
    imports can either."""
    above = {"manifoldneus": ("stages", "runner", "pipeline", "report", "bench"),
             "stages": ("runner", "pipeline", "report", "bench"), "runner": ("pipeline", "report", "bench")}
    for package, forbidden in above.items():
        files = sorted((runner.ROOT / package).rglob("*.py"))
        assert files, package
        for path in files:
            module = ".".join(path.relative_to(runner.ROOT).with_suffix("").parts).removesuffix(".__init__")
            names = runner.fingerprint._imported_names(path, module)
            assert not [n for n in names if n.split(".")[0] in forbidden], (path, sorted(names))
    # Inside the library: a sub-package imports itself, config and the floors below it only (the table;
    # docs/ARCHITECTURE.md, "The library"). geometry and data are the bottom floor together.
    may_import = {
        "geometry": {"data"},
        "data": {"geometry"},
        "neural": {"geometry", "data"},
        "sfm": {"geometry", "data", "scheduling"},
        "scheduling": set(),
        "output": {"geometry", "neural", "data"},
        "config": set(),
        "__init__": set(),
        "posefree": {"geometry", "neural", "sfm", "scheduling", "data", "output"},
    }
    library = runner.ROOT / "manifoldneus"
    crossings = set()
    for path in sorted(library.rglob("*.py")):
        rel = path.relative_to(library)
        floor = rel.parts[0] if len(rel.parts) > 1 else rel.stem
        assert floor in may_import, f"{rel}: a module outside the sub-packages"
        module = ".".join(("manifoldneus", *rel.with_suffix("").parts)).removesuffix(".__init__")
        for name in runner.fingerprint._imported_names(path, module):
            parts = name.split(".")
            if parts[0] != "manifoldneus" or len(parts) < 2 or parts[1] not in may_import:
                continue  # outside the library, or the package itself (its __version__)
            top = parts[1] in ("config", "posefree")  # else a sub-package: its module's name comes with it
            if parts[1] not in (floor, "config", *may_import[floor]) and (top or len(parts) > 2):
                crossings.add((module, ".".join(parts[:2] if top else parts[:3])))
    assert not crossings, sorted(crossings)


def test_callers_reach_the_runner_directly():
    """pipeline.py is the command line only: it re-exports nothing of the runner, and tests and benches
    call ``runner.X``, so the runner's API has one name."""
    import re

    assert not hasattr(pipeline, "Store") and not hasattr(pipeline, "resolve_params")
    for path in [*sorted((runner.ROOT / "tests").glob("*.py")), *sorted((runner.ROOT / "bench").glob("*.py"))]:
        used = set(re.findall(r"\bpipeline\.(\w+)", path.read_text())) - {"py", "main", "_parser"}
        assert not used, (path.name, sorted(used))


def test_no_module_edits_sys_path():
    """The project is installed (pyproject.toml) and the benches run as modules (`python -m bench.X`):
    no file puts a folder on sys.path to find the code, except profile_step's `--code`, which
    measures another checkout's package on purpose."""
    edits = []
    for path in [runner.ROOT / "pipeline.py", *sorted(runner.ROOT.glob("[mrsb]*/**/*.py"))]:
        for n, line in enumerate(path.read_text().splitlines(), 1):
            if "sys.path.insert" in line or "sys.path.append" in line:
                edits.append(f"{path.relative_to(runner.ROOT)}:{n}")
    assert [e.split(":")[0] for e in edits] == ["bench/profile_step.py"], edits


def test_shared_artifacts_are_named_by_their_readers_only():
    """The files several stages read are named in manifoldneus/data/artifacts.py only (its constants and
    readers, as hloc's one io module): no other module of the package, stage, runner or bench spells
    their names, so renaming one is a one-line change and no second reader can drift from the first."""
    import re

    from manifoldneus.data import artifacts

    # every file name artifacts.py defines, a new one included, and the rounds' folders in any spelling
    names = [v for k, v in vars(artifacts).items() if k.isupper() and isinstance(v, str) and "." in v]
    names.append(artifacts.ANCHOR_ROUND)
    assert len(names) > 20 and artifacts.MESH in names
    round_literal = re.compile(r"""["']round_[0-9{*]|/ *["']final["']""")  # "final" alone is also a JSON key
    for package in ("manifoldneus", "stages", "runner", "bench"):
        for path in sorted((runner.ROOT / package).rglob("*.py")):
            if path.name == "artifacts.py":
                continue
            text = path.read_text()
            assert not [n for n in names if f'"{n}"' in text or f"'{n}'" in text], path
            assert not round_literal.search(text), (path, round_literal.search(text))


@pytest.mark.parametrize("text, message", [
    ("run:\n\tseed: 1\n", r"params.yaml, line 2: not valid YAML .*indent with spaces, not tabs"),
    ("run: [1, 2\n", r"params.yaml, line \d: not valid YAML"),
    ("- a\n- b\n", r"params.yaml: the top level: expected a mapping"),
    ("gate: 5\n", r"params.yaml: section 'gate': expected a mapping"),
    ("", r"params.yaml is empty"),
])
def test_a_bad_params_file_is_named_with_its_line(tmp_path, artifacts, capsys, text, message):
    bad = tmp_path / "params.yaml"
    bad.write_text(text)
    assert pipeline.main(["run", "--scene", "synthetic", "--params", str(bad), "--artifacts", str(artifacts)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("error: ")
    import re
    assert re.search(message, err), err
    assert ("tabs" in err) == ("\t" in text)  # the hint about tabs only when a tab is the cause


def test_printed_commands_are_quoted_and_keep_the_runs_options(tmp_path, artifacts):
    """A hint pasted back acts on the same versions: --artifacts, --data-root, --set and the scene,
    shell-quoted (a folder with a space, a value with brackets)."""
    import shlex

    folder = tmp_path / "my photos"
    hint = runner.cli_hint("run", str(folder), "--until", "anchors", artifacts=artifacts, data_root=tmp_path,
                             overrides=["ingest.intrinsics=[500, 500, 96, 96]"], preset="neus-barf")
    words = shlex.split(hint)
    assert words[:3] == ["python", "pipeline.py", "run"]
    assert words[words.index("--scene") + 1] == str(folder) and words[words.index("--artifacts") + 1] == str(artifacts)
    assert words[words.index("--set") + 1] == "ingest.intrinsics=[500, 500, 96, 96]"
    assert words[words.index("--data-root") + 1] == str(tmp_path) and words[-2:] == ["--until", "anchors"]
    assert "--artifacts" not in runner.cli_hint("run", "scan24")  # the defaults are not repeated
    # the hint of a run whose upstream is missing carries the run's own options
    with pytest.raises(runner.PipelineError) as e:
        runner.run("synthetic", only="features", overrides=["ingest.downscale=2"], artifacts=artifacts)
    pasted = shlex.split(str(e.value).split("run: ", 1)[1])
    assert "ingest.downscale=2" in pasted and str(artifacts) in pasted


def test_a_missing_params_file_says_so(tmp_path, artifacts, capsys):
    assert pipeline.main(["status", "--scene", "synthetic", "--params", str(tmp_path / "nope.yaml")]) == 2
    assert f"parameter file {tmp_path / 'nope.yaml'} not found" in capsys.readouterr().err


def test_every_expected_failure_is_one_line(artifacts, capsys, monkeypatch):
    import stages.ingest as ingest

    args = ["run", "--scene", "synthetic", "--until", "ingest", "--artifacts", str(artifacts)]

    def fails(ctx):
        ctx.log.warning("a warning the user must see")
        raise ValueError("all views are black")

    monkeypatch.setattr(ingest, "run", fails)
    assert pipeline.main(args) == 2
    err = capsys.readouterr().err
    assert "[ingest] warning: a warning the user must see" in err  # a stage's warning reaches the console
    last = err.strip().splitlines()[-1]
    assert last.startswith("error: stage ingest failed: ValueError: all views are black (traceback in ")
    assert "Traceback" not in err and last.split("traceback in ")[1].split(";")[0].endswith("log.txt")
    with pytest.raises(ValueError):
        pipeline.main(["--debug", *args])

    def interrupted(ctx):
        raise KeyboardInterrupt

    monkeypatch.setattr(ingest, "run", interrupted)
    assert pipeline.main(args) == 130
    assert "interrupted: nothing half-written was published" in capsys.readouterr().err

    def read_only(self):
        raise PermissionError(13, "Permission denied", str(artifacts / "synthetic" / ".lock"))

    monkeypatch.setattr(runner.Store, "in_use", read_only)
    assert pipeline.main(args) == 2
    assert "error: no permission to write" in capsys.readouterr().err

    # a photo that cannot be read is an input: the fix is the photo's, not the artifacts folder's
    import numpy as np

    from manifoldneus.data import io, scenes

    photos = artifacts.parent / "photos"
    photos.mkdir()
    io.save_png(photos / "img_13.png", np.zeros((8, 8, 3), np.uint8))

    def unreadable(paths):
        raise PermissionError(13, "Permission denied", str(paths[0]))

    monkeypatch.setattr(scenes.io, "file_digests", unreadable)
    assert pipeline.main(["run", "--scene", str(photos), "--artifacts", str(artifacts)]) == 2
    err = capsys.readouterr().err
    assert f"error: no permission to read {photos / 'img_13.png'}: make it readable" in err


def test_a_run_ends_with_a_summary_and_colmap_logs_only_to_log_txt(artifacts, capfd):
    args = ["run", "--scene", "synthetic", "--artifacts", str(artifacts), *sum((["--set", s] for s in FAST_SYNTH), [])]
    assert pipeline.main([*args, "--until", "ground_truth"]) == 0
    out, _ = capfd.readouterr()
    assert "synthetic: 2 stages, 2 ran" in out and "  ingest             ran" in out
    assert pipeline.main([*args, "--only", "reference"]) == 0  # pycolmap (its upstream is ingest alone)
    out, err = capfd.readouterr()
    store = runner.Store(artifacts, "synthetic")
    log = (store.version_dir("reference", store.current("reference")) / "log.txt").read_text()
    assert "feature_extraction" in log  # COLMAP's own lines, in the stage's log...
    assert "feature_extraction" not in err + out  # ...not on the console
    assert pipeline.main([*args, "--until", "ground_truth"]) == 0
    assert "synthetic: 2 stages, 0 ran (0 s), 2 cached" in capfd.readouterr().out


def test_a_full_disk_is_one_line_naming_stage_and_file(artifacts, monkeypatch, capsys):
    """ENOSPC in a stage (its log unwritable too): one error line with the stage and the path, the
    partial version kept aside as .failed-* as for every failure, no .tmp-* left."""
    import errno
    import logging

    import stages.ingest as ingest

    def full(ctx):
        ctx.log.info("writing")
        monkeypatch.setattr(logging.StreamHandler, "flush", lambda self: (_ for _ in ()).throw(
            OSError(errno.ENOSPC, "No space left on device")))  # the stage's log.txt cannot be written either
        raise OSError(errno.ENOSPC, "No space left on device", str(ctx.out / "views.zarr"))

    monkeypatch.setattr(ingest, "run", full)
    argv = ["run", "--scene", "synthetic", "--until", "ingest", "--artifacts", str(artifacts)]
    argv += [w for o in FAST_SYNTH for w in ("--set", o)]
    assert pipeline.main(argv) == 2
    monkeypatch.undo()
    printed = capsys.readouterr().err
    assert "Traceback" not in printed and "Logging error" not in printed
    err = [line for line in printed.splitlines() if not line.startswith("[ingest] running")]
    assert len(err) == 1 and err[0].startswith("error: stage ingest: no space left on the disk writing ")
    assert "views.zarr" in err[0] and "--artifacts DIR" in err[0]
    stage_dir = artifacts / "synthetic" / "ingest"
    assert [p.name.startswith(".failed-") for p in stage_dir.iterdir()] == [True]



def test_every_option_of_every_command_says_what_it_does(capsys):
    import argparse

    parser = pipeline._parser()
    commands = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices
    assert {"run", "status", "gc", "view"} <= set(commands)
    for name, sub in [("", parser), *commands.items()]:
        silent = [a.option_strings or a.dest for a in sub._actions
                  if not isinstance(a, argparse._SubParsersAction) and not a.help and a.dest != "stage"]
        assert not silent, f"pipeline.py {name}: options without help {silent}"
    with pytest.raises(SystemExit) as e:
        pipeline.main(["--version"])
    assert e.value.code == 0 and capsys.readouterr().out.startswith(f"manifoldneus {manifoldneus.__version__} (torch ")


def test_a_stage_declaring_one_key_of_a_section_is_not_rerun_by_the_others(tmp_path):
    """mesh, export and evaluate declare run.device, not all of run: run.threads and run.seed do not
    enter their fingerprints (the rounds, which read them, do), and reading an undeclared key of
    the section is an error."""
    stages = runner.load_stages()
    assert stages["mesh"].keys_read()["run"] == {"device"} and stages["anchors"].keys_read()["run"] is None
    base = runner.resolve_params(stages, overrides=TINY)
    other = runner.resolve_params(stages, overrides=[*TINY, f"run.threads={base['run'].threads + 1}"])
    scene = runner.resolve_scene("synthetic")
    own_base, own_other = (runner.own_ingredients(stages, r, scene) for r in (base, other))
    changed = {name for name in stages if own_base[name]["params"] != own_other[name]["params"]}
    assert {"anchors", "successors"} <= changed and not changed & {"mesh", "export", "evaluate"}
    ctx = runner.Context(stages["mesh"], base, runner.Store(tmp_path, "x"), {}, tmp_path, scene, None)
    assert ctx.section("run").device == "cpu"
    with pytest.raises(runner.PipelineError, match=r"mesh reads run.threads without declaring it"):
        ctx.section("run").threads
    # the GT-pose reference meshes without the object crop: the crop's keys do not retrain it
    for key in ("meshing.silhouette_vote=0.5", "meshing.crop_to_object=off", "meshing.support_margin=0.1"):
        own_crop = runner.own_ingredients(stages, runner.resolve_params(stages, overrides=[*TINY, key]), scene)
        changed = {name for name in stages if own_base[name]["params"] != own_crop[name]["params"]}
        assert changed == {"mesh"}, (key, changed)
    broken = runner.Stage("mesh", stages["mesh"].module, (), ("meshing", "run.devices"), ())
    with pytest.raises(runner.PipelineError, match=r"declares \['run.devices'\]: no such key"):
        runner.stage_params(broken, base)


def _another_value(value):
    """A value of the same type that differs from `value` (None: no simple one)."""
    if isinstance(value, bool):
        return not value
    if isinstance(value, (int, float)):
        return value + 1
    if isinstance(value, str):
        return value + "x"
    if isinstance(value, list) and value:
        return [*value[:-1], _another_value(value[-1])] if not isinstance(value[-1], str) else value[:-1] or None
    return None


def test_every_key_reaches_exactly_the_stages_that_declare_it():
    """Change each key of every section, one at a time: the parameters a stage hashes change exactly
    when it declares that key (its whole section, or the key itself), so no key it does not read can
    make it stale and none it reads is left out."""
    import dataclasses

    stages = runner.load_stages()
    base = runner.resolve_params(stages, overrides=TINY)
    before = {name: runner.stage_params(stage, base) for name, stage in stages.items()}
    checked = 0
    for section, values in base.items():
        if not dataclasses.is_dataclass(values):  # the profile's and preset's names
            continue
        for f in dataclasses.fields(values):
            other = _another_value(getattr(values, f.name))
            if other is None:
                continue
            try:
                altered = {**base, section: dataclasses.replace(values, **{f.name: other})}
            except ParamError:  # out of its range: the next key
                continue
            for name, stage in stages.items():
                reads = stage.keys_read()
                declared = section in reads and (reads[section] is None or f.name in reads[section])
                changed = runner.stage_params(stage, altered) != before[name]
                assert changed == declared, (name, f"{section}.{f.name}")
            checked += 1
    assert checked > 100


def test_a_command_starts_without_the_imports_only_training_needs():
    """Every command imports the runner and every stage's module; torch._dynamo (which roma imports) and
    scipy.stats took 2-4 of a status's 8 s on this machine, so they are imported where they are used."""
    import subprocess
    import sys

    heavy = ("torch._dynamo", "scipy.stats", "roma")
    code = f"import sys, runner; runner.load_stages(); print([m for m in {heavy!r} if m in sys.modules])"
    out = subprocess.run([sys.executable, "-c", code], cwd=runner.ROOT, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]"


def test_the_installed_command_is_the_pipelines_command_line(tmp_path):
    """`make setup` installs `manifoldneus` beside the venv's python: the same CLI as pipeline.py."""
    import subprocess
    import sys
    from pathlib import Path

    command = Path(sys.executable).parent / "manifoldneus"
    assert command.is_file(), "pyproject.toml's [project.scripts] installs it (make setup)"
    out = subprocess.run([str(command), "status", "--scene", "synthetic", "--artifacts", str(tmp_path / "art")],
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0 and out.stdout.startswith("ingest") and "never computed" in out.stdout
    usage = subprocess.run([str(command), "--help"], capture_output=True, text=True, timeout=120).stdout
    assert usage.startswith("usage: manifoldneus ")


def test_the_artifacts_root_is_set_once_by_the_environment(tmp_path):
    """MANIFOLDNEUS_ARTIFACTS names the artifacts folder for every command run from any folder; --artifacts
    still wins."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parent.parent
    env = {**os.environ, "MANIFOLDNEUS_ARTIFACTS": str(tmp_path / "runs")}
    cmd = [sys.executable, str(root / "pipeline.py"), "run", "--scene", "synthetic", "--until", "ingest",
           "--set", "ingest.synthetic_views=6", "--set", "ingest.synthetic_resolution=32"]
    out = subprocess.run(cmd, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    assert (tmp_path / "runs" / "synthetic" / "ingest" / "current").is_symlink()
    out = subprocess.run([*cmd, "--artifacts", str(tmp_path / "other")], cwd=tmp_path, env=env, capture_output=True,
                         text=True, timeout=300)
    assert out.returncode == 0 and (tmp_path / "other" / "synthetic" / "ingest" / "current").is_symlink()


def test_torch_is_held_at_the_tested_build_only_by_make_setup():
    """pyproject.toml admits a user's own torch (a CUDA build of another version); constraints.txt, which make
    setup installs with, holds the venv at the tested build, and that is the torch installed here."""
    import importlib.metadata
    import tomllib
    from pathlib import Path

    from packaging.requirements import Requirement

    root = Path(__file__).resolve().parent.parent
    wanted = [Requirement(r) for r in tomllib.loads((root / "pyproject.toml").read_text())["project"]["dependencies"]]
    torch_req = next(r for r in wanted if r.name == "torch")
    pins = [Requirement(line) for line in (root / "constraints.txt").read_text().splitlines()
            if line.strip() and not line.startswith("#")]
    pin = next(r for r in pins if r.name == "torch")
    tested = next(iter(pin.specifier)).version
    assert torch_req.specifier.contains("2.5.1") and torch_req.specifier.contains(tested)
    assert "-c constraints.txt" in (root / "Makefile").read_text()
    assert importlib.metadata.version("torch").split("+")[0] == tested


def test_a_stage_says_how_long_earlier_runs_of_it_and_the_rest_took(tmp_path):
    """The estimate printed as a stage starts: its newest version's wall time in this scene, and at most the
    sum of the newest versions of it and the stages after it; nothing for a stage this scene never ran."""
    import os

    import runner.execute

    store = runner.store.Store(tmp_path, "scene")
    for stage, versions in {"anchors": [("old", 900.0), ("new", 80.0)], "surface": [("a", 200.0)]}.items():
        for k, (fp, seconds) in enumerate(versions):
            folder = store.version_dir(stage, fp)
            folder.mkdir(parents=True)
            (folder / "manifest.json").write_text(json.dumps({"wall_seconds": seconds}))
            os.utime(folder / "manifest.json", (1e9 + k, 1e9 + k))  # the later one is the newer
    assert store.recorded_seconds("anchors") == 80.0 and store.recorded_seconds("mesh") is None
    assert runner.execute.expected_time(store, ["anchors", "surface", "mesh"]) == \
        " (earlier runs: about 80 s, at most 5 min for the run's rest)"
    assert runner.execute.expected_time(store, ["surface"]) == " (earlier runs: about 3 min)"
    assert runner.execute.expected_time(store, ["mesh", "surface"]) == ""
