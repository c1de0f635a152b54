"""The project installed as a user installs it: a wheel built from the checkout, pip-installed (not editable)
into a fresh virtual environment, its `manifoldneus` command run from a folder outside the checkout."""
import json
import shutil
import subprocess
import sys
import sysconfig
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parent.parent


def test_the_installed_command_runs_from_any_folder_with_its_own_defaults(tmp_path):
    clone = tmp_path / "clone"  # what a fresh clone holds (no build/ left by an earlier build)
    shutil.copytree(ROOT, clone, symlinks=True, ignore=shutil.ignore_patterns(
        ".git", ".venv", "artifacts", "build", "*.egg-info", "__pycache__", ".pytest_cache", "bench", "docs", "tests"))
    wheels = tmp_path / "wheels"
    subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q", str(clone),
                    "-w", str(wheels)], check=True, capture_output=True)
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True)
    python = venv / "bin" / "python"
    # the dependencies are this environment's (nothing to download): the new one sees them through a .pth
    purelib = subprocess.run([python, "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                             check=True, capture_output=True, text=True).stdout.strip()
    (Path(purelib) / "dependencies.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    subprocess.run([python, "-m", "pip", "install", "-q", "--no-deps", "--no-index", *map(str, wheels.glob("*.whl"))],
                   check=True, capture_output=True)
    elsewhere = tmp_path / "photos"
    elsewhere.mkdir()
    run = subprocess.run([venv / "bin" / "manifoldneus", "run", "--scene", "synthetic", "--until", "features",
                          "--set", "ingest.synthetic_views=6", "--set", "ingest.synthetic_resolution=48",
                          "--set", "ingest.synthetic_surface_points=1000"],
                         cwd=elsewhere, capture_output=True, text=True, env={"PATH": "/usr/bin:/bin"})
    assert run.returncode == 0, run.stderr[-2000:]
    # its versions land under the folder it ran in, not in site-packages, with the checkout's parameters
    manifest = json.loads(next((elsewhere / "artifacts" / "synthetic" / "ingest").glob("*/manifest.json")).read_text())
    assert manifest["profile"] == yaml.safe_load((ROOT / "params.yaml").read_text())["profile"]
    assert manifest["params"]["ingest"]["synthetic_views"] == 6
    assert not (Path(purelib) / "artifacts").exists()
