#!/usr/bin/env python
"""manifoldneus pipeline: a cached DAG of stages, each writing a versioned artifact (the runner: runner/).

    python pipeline.py run --scene S [--until STAGE | --only STAGE] [--set sec.key=value ...]
                           [--force STAGE] [--profile fast|quick|paper] [--preset NAME]
    python pipeline.py status --scene S
    python pipeline.py show --scene S STAGE
    python pipeline.py params-diff --scene S STAGE
    python pipeline.py verify --scene S
    python pipeline.py view --scene S [--preset NAME] [--out FILE] [--open] [--screenshot PNG]
    python pipeline.py report --scene S [--out DIR]
    python pipeline.py gc [--scene S] [--dry-run]

This file is the command line only; what it calls (and what scripts, benches and tests import) is the
package ``runner``, whose docstring describes the artifact layout and the fingerprints.
"""
from __future__ import annotations

import argparse
import contextlib
import errno
import importlib.metadata
import logging
import os
import signal
import sys
import threading
from pathlib import Path

from runner import executor
from runner.common import DEFAULT_ARTIFACTS, DEFAULT_PARAMS, PipelineError, Terminated, _raise_terminated
from runner.execute import cli_hint, run
from runner.inspect import run_summary, show, status, verify, view
from runner.store import gc

from manifoldneus import __version__
from manifoldneus.config import ParamError
from manifoldneus.data.scenes import SceneError


# ---------------------------------------------------------------------------- CLI


def _parser() -> argparse.ArgumentParser:
    # "manifoldneus" when installed as a command, "pipeline.py" from the checkout
    prog = "manifoldneus" if Path(sys.argv[0]).name == "manifoldneus" else "pipeline.py"
    p = argparse.ArgumentParser(prog=prog, description=__doc__.split("\n")[0])
    p.add_argument("--debug", action="store_true", help="show the traceback of a failure")
    p.add_argument("--version", action="version", version=f"manifoldneus {__version__} (torch "
                   f"{importlib.metadata.version('torch')}, Python {sys.version.split()[0]})")
    sub = p.add_subparsers(dest="command", required=True)

    def common(sp, params=True, scenes=False):
        sp.add_argument("--scene", default=None if scenes else "synthetic", action="append" if scenes else "store",
                        help="scene name (synthetic, synthetic-<seed>, scan24, ...) or a folder"
                             + ("; repeat it to run several scenes (default synthetic)" if scenes else ""))
        sp.add_argument("--data-root", type=Path, default=None, help="data root (default $MANIFOLDNEUS_DATA or ../shared/data)")
        sp.add_argument("--artifacts", type=Path, default=DEFAULT_ARTIFACTS,
                        help="the artifacts folder: every stage's versions, per scene (default $MANIFOLDNEUS_ARTIFACTS, "
                             "else the checkout's artifacts/)")
        if params:
            sp.add_argument("--params", type=Path, default=DEFAULT_PARAMS,
                            help="the parameter file (default ./params.yaml)")
            sp.add_argument("--set", dest="overrides", action="append", default=[], metavar="SECTION.KEY=VALUE",
                            help="override one parameter for this command (repeat it for several); "
                                 "docs/USAGE.md and `pipeline.py params-diff STAGE` name the keys")
            sp.add_argument("--profile", default=None, help="fast | quick | paper | gpu (default: params.yaml's `profile`)")
            sp.add_argument("--preset", default=None, help="a named preset from params.yaml (e.g. neus-barf); "
                                                           "its versions keep their own `current@PRESET` pointers")

    sp = sub.add_parser("run", help="bring stages up to date")
    common(sp, scenes=True)
    executor.add_arguments(sp)
    g = sp.add_mutually_exclusive_group()
    g.add_argument("--until", help="run this stage and the stages it depends on (not the others listed before it)")
    g.add_argument("--only", help="run just this stage (its upstream must be up to date)")
    sp.add_argument("--force", action="append", default=[], metavar="STAGE", help="recompute even if cached")
    sp = sub.add_parser("status", help="which stages are fresh, stale, cached or missing, and why")
    common(sp)
    sp = sub.add_parser("show", help="what a stage's current artifact holds")
    common(sp, params=False)
    sp.add_argument("--preset", default=None, help="the versions of a named preset of params.yaml (its `current@PRESET`)")
    sp.add_argument("stage", help="a stage name (pipeline.py status lists them)")
    sp = sub.add_parser("params-diff", help="what changed since a stage's current version")
    common(sp)
    sp.add_argument("stage", help="a stage name (pipeline.py status lists them)")
    sp = sub.add_parser("verify", help="re-hash the current versions' files against their manifests")
    common(sp, params=False)
    sp.add_argument("--preset", default=None, help="the versions of a named preset of params.yaml (its `current@PRESET`)")
    sp = sub.add_parser("view", help="write the run's viewer page (mesh and cameras in a browser) and print its path")
    common(sp, params=False)
    sp.add_argument("--preset", default=None, help="the versions of a named preset of params.yaml (its `current@PRESET`)")
    sp.add_argument("--out", type=Path, default=None, help="the HTML file (default: <artifacts>/<scene>/viewer/viewer.html)")
    sp.add_argument("--max-faces", type=int, default=None, help="decimate the mesh to at most this many triangles")
    sp.add_argument("--open", action="store_true", help="also open the page in the default browser")
    sp.add_argument("--screenshot", type=Path, default=None, metavar="PNG",
                    help="also render the page in headless Chromium and save what it shows (1200x800)")
    sp = sub.add_parser("report", help="write report.md comparing the systems on a scene, from its artifacts (never trains)")
    common(sp, params=False)
    sp.add_argument("--out", type=Path, default=None, help="output folder (default: <artifacts>/<scene>/report)")
    sp = sub.add_parser("gc", help="delete artifact versions no longer current (inside the artifacts folder only)")
    sp.add_argument("--scene", default=None, help="only this scene, resolved as `run` resolves it (default: every scene)")
    sp.add_argument("--data-root", type=Path, default=None, help="data root (default $MANIFOLDNEUS_DATA or ../shared/data)")
    sp.add_argument("--artifacts", type=Path, default=DEFAULT_ARTIFACTS, help="the artifacts folder (default $MANIFOLDNEUS_ARTIFACTS, else the checkout's artifacts/)")
    sp.add_argument("--dry-run", action="store_true", help="list what would be removed, remove nothing")
    sp.add_argument("--drop-interrupted", action="store_true",
                    help="also give up what killed runs left to resume from (their records in <scene>/.runs)")
    return p


def main(argv: list[str] | None = None) -> int:
    """The CLI: every expected failure is one `error:` line and exit code 2 (130 for Ctrl-C);
    ``--debug`` re-raises it with its traceback."""
    args = _parser().parse_args(argv)
    # a log file that cannot be written (a full disk) must not print logging's own tracebacks
    logging.raiseExceptions = bool(args.debug)
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, _raise_terminated)
    try:
        return _command(args)
    except KeyboardInterrupt as e:
        if args.debug:
            raise
        why = "terminated (SIGTERM)" if isinstance(e, Terminated) else "interrupted"
        # on a line of its own, after whatever progress bar was drawing
        print(f"\n{why}: nothing half-written was published; run the same command again to go on "
              "(trainings resume from their checkpoints)", file=sys.stderr)
        return 143 if isinstance(e, Terminated) else 130
    except BrokenPipeError:  # the reader went away (`status | head -3`): stop quietly, as other tools do
        with contextlib.suppress(OSError, ValueError, AttributeError):  # no flush at exit into the closed pipe
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 128 + signal.SIGPIPE
    except (PipelineError, ParamError, SceneError) as e:
        if args.debug:
            raise
        print(f"error: {e}", file=sys.stderr)
        return 2
    except PermissionError as e:
        if args.debug:
            raise
        artifacts = Path(getattr(args, "artifacts", None) or DEFAULT_ARTIFACTS).resolve()
        if e.filename and not Path(e.filename).resolve().is_relative_to(artifacts):  # an input, being read
            print(f"error: no permission to read {e.filename}: make it readable (chmod u+r) or move it out of the "
                  "scene's folder", file=sys.stderr)
        else:
            print(f"error: no permission to write {e.filename}: choose a writable artifacts folder with --artifacts DIR",
                  file=sys.stderr)
        return 2
    except Exception as e:  # noqa: BLE001 - a stage's failure: one line, the traceback is in its log
        if args.debug:
            raise
        stage, log_path = getattr(e, "stage_failed", (None, None))
        if isinstance(e, OSError) and e.errno in (errno.ENOSPC, errno.EDQUOT):
            print(f"error: {f'stage {stage}: ' if stage else ''}no space left on the disk writing "
                  f"{e.filename or '?'}; nothing was published"
                  f"{f' (what it had written: {log_path.parent})' if log_path else ''}. Free space (python pipeline.py "
                  f"gc drops versions no pointer uses) or run with --artifacts DIR on a larger disk, then the same "
                  f"command again", file=sys.stderr)
            return 2
        where = f"stage {stage} failed: " if stage else ""
        hint = f" (traceback in {log_path}; --debug prints it here)" if log_path else " (--debug prints the traceback)"
        print(f"error: {where}{type(e).__name__}: {e}{hint}", file=sys.stderr)
        return 2


def run_scenes(args) -> int:
    """`run` of one scene here, as before; of several (or with --executor), one task per scene."""
    scenes = list(dict.fromkeys(args.scene or ["synthetic"]))
    kwargs = dict(until=args.until, only=args.only, overrides=args.overrides, force=args.force, profile=args.profile,
                  preset=args.preset, artifacts=args.artifacts, params_path=args.params, data_root=args.data_root)
    if len(scenes) == 1 and args.executor == "in-process":
        print(run_summary(scenes[0], run(scenes[0], **kwargs), args.artifacts, args.data_root, args.preset))
        return 0
    outcomes = []
    for outcome in executor.run_all([executor.RunSpec(s, s, kwargs) for s in scenes], args.executor, args.workers):
        outcomes.append(outcome)
        if outcome.report is not None and not outcome.error:
            print(run_summary(outcome.name, outcome.report, args.artifacts, args.data_root, args.preset) + "\n")
    failed = executor.failures(outcomes)
    if failed:
        print(f"error: {failed}", file=sys.stderr)
    return 1 if failed else 0


def _command(args) -> int:
    artifacts = getattr(args, "artifacts", None)
    if artifacts is not None and Path(artifacts).exists() and not Path(artifacts).is_dir():
        raise PipelineError(f"--artifacts {artifacts} is a file, not a folder: name a folder for the artifacts "
                            "(it is created when missing)")
    if args.command == "run":
        return run_scenes(args)
    elif args.command == "status":
        for name, (state, reasons) in status(args.scene, args.overrides, args.profile, args.preset,
                                             args.artifacts, args.params, args.data_root).items():
            print(f"{name:<18} {state:<8} {'; '.join(reasons)}")
    elif args.command == "show":
        print(show(args.scene, args.stage, args.artifacts, args.data_root, args.preset))
    elif args.command == "params-diff":
        states = status(args.scene, args.overrides, args.profile, args.preset, args.artifacts, args.params,
                        args.data_root)
        if args.stage not in states:
            raise PipelineError(f"unknown stage {args.stage!r} (stages: {', '.join(states)})")
        state, reasons = states[args.stage]
        print(f"{args.stage}: {state}")
        for r in reasons:
            print(f"  {r}")
    elif args.command == "verify":
        results = verify(args.scene, args.artifacts, args.data_root, args.preset)
        for name, (state, problems) in results.items():
            print(f"{name:<18} {state}")
            for problem in problems:
                print(f"    {problem}")
        damaged = [n for n, (state, _) in results.items() if state == "DAMAGED"]
        if damaged:
            forced = [w for name in damaged for w in ("--force", name)]
            print("rebuild: " + cli_hint("run", args.scene, *forced, artifacts=args.artifacts, data_root=args.data_root,
                                         preset=args.preset))
            return 1
    elif args.command == "view":
        path, held = view(args.scene, args.artifacts, args.data_root, args.preset, args.out, args.max_faces)
        decimated = "" if held["faces"] == held["faces_full"] else f" decimated from {held['faces_full']}"
        print(f"{path}  ({held['bytes'] / 2**20:.1f} MiB: {held['optimised']} optimised cameras, "
              f"{held['held_out_drawn']} held-out cameras, mesh of {held['faces']} triangles{decimated})")
        if args.screenshot:
            from manifoldneus.output import viewer

            shown = viewer.render_in_browser(path, args.screenshot)
            print(f"{args.screenshot}  (the page in headless Chromium: {shown['attributes'].get('cameras-drawn')} "
                  f"cameras drawn{'; page errors: ' + shown['attributes']['errors'] if 'errors' in shown['attributes'] else ''})")
        if args.open:
            import webbrowser

            webbrowser.open(path.resolve().as_uri())
    elif args.command == "report":
        from report import build_report

        print(f"wrote {build_report(args.scene, args.artifacts, args.out, args.data_root)}")
    elif args.command == "gc":
        removed = gc(args.artifacts, args.scene, args.data_root, args.dry_run, args.drop_interrupted)
        verb = "would remove" if args.dry_run else "removed"
        for path, size in removed.items():
            print(f"{verb} {path}  ({size / 2**20:.1f} MiB)")
        print(f"{verb} {len(removed)} old version(s), {sum(removed.values()) / 2**20:.1f} MiB")
    return 0


if __name__ == "__main__":
    sys.exit(main())
