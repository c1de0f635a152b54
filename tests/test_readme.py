"""README.md is a short user's guide whose figures come from the bench JSON.

- at most 250 lines;
- its generated parts (results block, headline), and docs/REFINEMENT.md's current figures, equal what
  `make results` writes from bench/*.json;
- outside the generated parts no word looks like a commit hash, and no word anywhere names a commit;
- every relative link and every docs/ path it names is a file in the repository.
"""
from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path

import pytest

from bench import bench, results_md

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
MAX_LINES = 250
HEX_WORD = re.compile(r"\b[0-9a-f]{7,40}\b")


def readme() -> str:
    return README.read_text(encoding="utf-8")


def outside_generated(text: str) -> str:
    """`text` without what lies between the generated blocks' markers."""
    for begin, end in ((results_md.BEGIN, results_md.END), (results_md.HEADLINE_BEGIN, results_md.HEADLINE_END)):
        start, stop = text.find(begin), text.find(end)
        if start >= 0 and stop > start:
            text = text[:start] + text[stop + len(end):]
    return text


def test_readme_has_at_most_250_lines():
    n = len(readme().splitlines())
    assert n <= MAX_LINES, f"README.md has {n} lines (at most {MAX_LINES}): move detail to docs/"


def test_results_block_is_what_make_results_writes():
    text = readme()
    block = results_md.between_markers(text)
    assert block is not None, f"README.md needs {results_md.BEGIN} ... {results_md.END}"
    expected = results_md.results_markdown(bench.DEFAULT_OUT_DIR).strip()
    assert block == expected, "README's results block is not what the bench JSON gives: run `make results`"


def test_headline_is_what_make_results_writes():
    text = readme()
    head = results_md.between_markers(text, results_md.HEADLINE_BEGIN, results_md.HEADLINE_END)
    assert head is not None, "README.md's headline result is generated: it needs the headline markers"
    assert head == results_md.headline_markdown(bench.DEFAULT_OUT_DIR).strip(), "run `make results`"
    # and the whole file is a fixed point of `make results`
    assert results_md.render_readme(text, bench.DEFAULT_OUT_DIR) == text


def test_the_refinement_page_block_is_what_make_results_writes():
    text = (ROOT / "docs" / "REFINEMENT.md").read_text(encoding="utf-8")
    block = results_md.between_markers(text, results_md.REFINEMENT_BEGIN, results_md.REFINEMENT_END)
    assert block is not None, "docs/REFINEMENT.md's current figures are generated: it needs the refinement markers"
    assert block == results_md.refinement_markdown(bench.DEFAULT_OUT_DIR).strip(), "run `make results`"
    assert "| scene | seeds |" in block  # the table itself, not only a note


def test_no_commit_hash_in_readme():
    text = readme()
    outside = HEX_WORD.findall(outside_generated(text))
    # pure digits (a year, a count) are numbers, not hashes
    suspects = [w for w in outside if not w.isdigit()]
    assert not suspects, f"README names what look like commit hashes outside its generated parts: {suspects}"
    if shutil.which("git") is None or not (ROOT / ".git").exists():
        pytest.skip("no git checkout to resolve words against")
    commits = [w for w in set(HEX_WORD.findall(text))
               if subprocess.run(["git", "cat-file", "-e", f"{w}^{{commit}}"], cwd=ROOT,
                                 capture_output=True).returncode == 0]
    assert not commits, f"README names commits {commits}: history belongs in docs/CHANGELOG.md"


def anchors(markdown: str) -> set[str]:
    """GitHub's anchors of a markdown file's headings (lower case, punctuation dropped, spaces -> '-')."""
    return {re.sub(r"[^\w\- ]", "", h.strip().lower()).replace(" ", "-")
            for h in re.findall(r"^#+ (.+)$", markdown, flags=re.M)}


def test_relative_links_and_docs_paths_exist():
    text = readme()
    links = []
    for target in re.findall(r"\]\(([^)\s]+)\)", text):  # [text](target) and ![alt](target)
        if re.match(r"^[a-z][a-z0-9+.-]*:", target):
            continue  # http:, mailto:
        path, _, fragment = target.partition("#")
        links.append((path, fragment))
    links += [(p, "") for p in re.findall(r"(?<![\w/.])(docs/[\w./-]+\.(?:md|png))", text)]
    assert any(p for p, _ in links), "README links no docs at all?"
    missing = sorted({p for p, _ in links if p and not (ROOT / p).is_file()})
    assert not missing, f"README links files that do not exist: {missing}"
    bad = sorted({f"{p}#{f}" for p, f in links
                  if f and f not in anchors(text if not p else (ROOT / p).read_text(encoding="utf-8"))})
    assert not bad, f"README links anchors with no heading: {bad}"


def test_a_bench_that_ran_on_the_fallback_kernel_says_so():
    """The fused grid kernel failing to load is only a warning in a run's log: a bench JSON records
    the kernel its process used, and README's provenance line names the fallback."""
    assert results_md.kernel_note({"grid_kernel": "fused"}) == results_md.kernel_note({}) == ""
    note = results_md.kernel_note({"grid_kernel": "torch: ImportError: no compiler"})
    assert "grid_sample" in note and "ImportError: no compiler" in note
    assert bench.grid_kernel_used() in ("fused",) or bench.grid_kernel_used().startswith("torch: ")


def test_scenes_in_the_same_units_share_one_table():
    """Two scenes in millimetres (scan24, scan24_idr) and one in scene units: two tables, not three
    (README's line budget), each scene's rows under its table's header."""
    import copy
    import json

    mm = json.loads((ROOT / "bench/scan24/2026-11-25.json").read_text())
    other_mm = copy.deepcopy(mm)
    other_mm["scene"] = "scan24_idr"
    for result, spread in ((mm, 0.06), (other_mm, 0.05)):  # each reference's own colour spread
        for system in result["systems"].values():
            system["reference_colour_spread"] = spread
    unit = json.loads((ROOT / "bench/synthetic/2026-11-26.json").read_text())
    text = results_md.systems_markdown([(Path("a.json"), mm), (Path("b.json"), unit), (Path("c.json"), other_mm)], ROOT)
    headers = [line for line in text.splitlines() if line.startswith("| scene |")]
    assert len(headers) == 2 and "(mm)" in headers[0] and "(unit)" in headers[1]
    first = text.split(headers[1])[0]
    assert "| scan24 | ManifoldNeuS" in first and "| scan24_idr | ManifoldNeuS" in first
    assert "| synthetic |" not in first and "| synthetic | ManifoldNeuS" in text.split(headers[1])[1]
    # a footnote written for some of the scenes names them; one written for all of them does not
    notes = [line for line in text.splitlines() if line[:1].isdigit()]
    assert any(n.split(". ", 1)[1].startswith("synthetic: Chamfer against the exact surface") for n in notes)
    assert any(n.split(". ", 1)[1].startswith("scan24, scan24_idr: Chamfer against the mesh") for n in notes)
    # the references' colour spreads, different per scene, share one footnote
    spread_notes = [n.split(". ", 1)[1] for n in notes if "own colour spread" in n]
    assert spread_notes == ["The reference surface's own colour spread: scan24 0.0600, scan24_idr 0.0500."]
    assert any(n.split(". ", 1)[1].startswith("Mean ± std over the seeds") for n in notes)


def test_a_bench_measured_with_other_defaults_is_not_shown_as_today(tmp_path):
    """A bench JSON records what every system resolved its parameters to; README shows a scene only
    while the checkout resolves them the same, and otherwise names the parameters that changed."""
    import json

    today = json.loads(json.dumps(bench.resolved_params()))
    assert set(today) == {s.preset or "default" for s in bench.SYSTEMS.values()}
    current = {"resolved_params": today}
    assert results_md.changed_defaults(current) == [] and results_md.stale_note(current, "x") == ""
    assert results_md.changed_defaults({}) == []  # older JSON without the record: nothing to compare
    older = json.loads(json.dumps(current))
    older["resolved_params"]["default"]["field.grid_max_res"] = 64
    older["resolved_params"]["neus-barf"]["gate.lam"] = 0.5
    older["resolved_params"]["default"]["field.a_key_removed_since"] = 1  # the behaviour it set is gone
    newer = json.loads(json.dumps(current))
    del newer["resolved_params"]["default"]["field.grid_max_res"]  # a key added since keeps the old behaviour
    assert results_md.changed_defaults(newer) == []
    assert results_md.changed_defaults(older) == ["field.grid_max_res", "gate.lam (neus-barf)",
                                                  "field.a_key_removed_since removed"]
    for scene, result in (("scan24", current), ("synthetic", older)):
        full = json.loads((ROOT / "bench/scan24/2026-11-26.json").read_text())
        full.update(result, scene=scene)
        (tmp_path / scene).mkdir()
        (tmp_path / scene / "2026-11-26.json").write_text(json.dumps(full))
    text = results_md.results_markdown(tmp_path, tmp_path)
    assert "| scan24 | ManifoldNeuS" in text and "| synthetic |" not in text
    assert "synthetic: `synthetic/2026-11-26.json` was measured with other defaults" in text
    assert "(field.grid_max_res, gate.lam (neus-barf), field.a_key_removed_since removed)" in text
    assert "make bench SCENE=synthetic" in text


def test_the_headline_sets_its_rotation_errors_beside_the_alignment_free_ones(tmp_path):
    """The headline's rotation errors are measured after a Sim3 fitted on the camera centres; beside them
    it prints ManifoldNeuS's and SfM-all's PRE_r from the scene's `make bench`, while that bench resolves
    its parameters as the checkout does."""
    import json

    full = json.loads((ROOT / "bench/scan24/2026-11-26.json").read_text())
    full["resolved_params"] = json.loads(json.dumps(bench.resolved_params()))
    refine = json.loads(results_md.refine_files(ROOT / "bench")[-1].read_text())
    refine["resolved_params"] = full["resolved_params"]
    (tmp_path / "scan24").mkdir()
    (tmp_path / "refine").mkdir()
    (tmp_path / "refine" / "refine.json").write_text(json.dumps(refine))
    pre_r = {k: full["systems"][k]["spread"]["pre_r_deg_mean"]["mean"] for k in ("manifoldneus", "sfm-all")}
    for changed in (False, True):
        if changed:
            full["resolved_params"]["default"]["field.grid_max_res"] = 64
        (tmp_path / "scan24" / "2026-11-26.json").write_text(json.dumps(full))
        text = results_md.headline_markdown(tmp_path, tmp_path)
        shown = "which no alignment changes" in text
        assert shown != changed
        assert all((f"{v:.3f} ± " in text or f"{v:.3f} for" in text) == shown for v in pre_r.values())


def test_the_project_speaks_of_itself_by_date():
    """Docs, code, bench records and file names date what they say (2026-11-27); none counts the periods
    of work by ordinal or cites the tracker's entries by number (the words are spelled apart below: this
    file is scanned too)."""
    ordinal = (r"first|second|third|fourth|fifth|sixth|seventh|eighth|ninth|tenth|eleventh|twelfth|thirteenth|"
               r"fourteenth|fifteenth|sixteenth|seventeenth|eighteenth|nineteenth|twentieth|\d+(st|nd|rd|th)")
    period, entry, word = "ses" + "sion", "iss" + "ue", "sitt" + "ing"
    banned = re.compile(rf"\b({ordinal})[ -]{period}\b|\b{entry}s? #?\d+\b|{word}", re.IGNORECASE)
    files = subprocess.run(["git", "ls-files"], cwd=ROOT, capture_output=True, text=True, check=True).stdout.split()
    bad = [f for f in files if re.search(rf"{period}|{word}|{entry}-?\d", f, re.IGNORECASE)]
    for f in files:
        if f.endswith((".md", ".py", ".json", ".yaml", ".toml")) or f in ("Makefile", ".ci/run"):
            text = (ROOT / f).read_text(errors="replace")
            bad += [f"{f}:{text.count(chr(10), 0, m.start()) + 1}: {m.group(0)}" for m in banned.finditer(text)]
    assert not bad, "\n".join(bad[:20])


def test_a_default_no_run_of_a_bench_reads_leaves_its_figures_shown():
    """The crop to the object's keys are read only where the surface is cropped (no masks), the photo masks' only
    without the layout's masks: changed, they stale the photos-alone runs of a bench, not its masked ones; and
    only the presets a bench ran count."""
    import json

    from bench import bench_refine
    from manifoldneus.output import evaluation

    then = {"resolved_params": json.loads(json.dumps(bench.resolved_params()))}
    assert then["resolved_params"]["default"]["ingest.load_masks"] and not then["resolved_params"]["photos-alone"][
        "ingest.load_masks"]
    for preset in then["resolved_params"].values():
        preset["meshing.silhouette_dilation"] += 1.0
    assert "silhouette_dilation" in evaluation.CROP_KEYS
    assert results_md.changed_defaults(then) == ["meshing.silhouette_dilation (photos-alone)"]
    assert results_md.changed_defaults(then, bench_refine.PRESETS) == []
    assert set(bench.resolved_params(presets=bench_refine.PRESETS)) == set(bench_refine.PRESETS)
    # a masked run told to crop reads them
    then["resolved_params"]["default"]["meshing.crop_to_object"] = "on"
    assert "meshing.silhouette_dilation" in results_md.changed_defaults(then, bench_refine.PRESETS)
    # the masks made from the photos: read only where the layout's are not loaded
    for preset in then["resolved_params"].values():
        preset["surface.photo_mask_vote"] += 0.05
    assert "surface.photo_mask_vote (photos-alone)" in results_md.changed_defaults(then)
    assert "surface.photo_mask_vote" not in results_md.changed_defaults(then, bench_refine.PRESETS)


def test_a_later_bench_of_some_systems_replaces_their_rows(tmp_path):
    """`make bench ARGS="--systems photos-alone"` after a full bench: README shows the full bench with those
    rows, their seeds and targets from the later file, and says so; an earlier one, one on other seeds and one
    measured with other parameters than the checkout's do not pass as today's figures."""
    import json

    full = json.loads((ROOT / "bench/scan24/2026-11-28.json").read_text())
    (tmp_path / "scan24").mkdir()
    (tmp_path / "scan24" / "2026-11-28.json").write_text(json.dumps(full))

    def subset(name: str, date: str, chamfer: float, seeds=(0, 1, 2)) -> dict:
        sub = json.loads(json.dumps(full))
        sub.update(date=date, seeds=list(seeds), systems={"photos-alone": sub["systems"]["photos-alone"]},
                   per_seed={s: {"photos-alone": {**r["photos-alone"], "chamfer_units": chamfer}}
                             for s, r in sub["per_seed"].items()})
        sub["systems"]["photos-alone"]["chamfer_units"] = chamfer
        (tmp_path / "scan24" / name).write_text(json.dumps(sub))
        return sub

    before = results_md.results_markdown(tmp_path, tmp_path)
    assert "photos alone's Chamfer <= 1.3 x the calibrated masked run's: MISSED" in before
    subset("2026-11-27-photos-alone.json", "2026-11-27T09:00:00", 0.5)   # older than the full bench
    subset("2026-11-29-photos-alone-two-seeds.json", "2026-11-29T08:00:00", 0.5, seeds=(0, 1))
    assert results_md.results_markdown(tmp_path, tmp_path) == before
    sub = subset("2026-11-29-photos-alone.json", "2026-11-29T09:00:00", 1.25)
    text = results_md.results_markdown(tmp_path, tmp_path)
    assert "photos alone's Chamfer <= 1.3 x the calibrated masked run's: met (seed 0 1.25 vs" in text
    assert ("its ManifoldNeuS, photos alone rows measured again 2026-11-29 09:00:00 "
            "(`scan24/2026-11-29-photos-alone.json` with `--set run.threads=1`)") in text
    row = next(line for line in text.splitlines() if "| ManifoldNeuS, photos alone |" in line)
    assert "| 1.25 ±" in row
    assert text.count("| scan24 | ManifoldNeuS |") == 1  # the masked rows stay the full bench's
    # measured with a value the checkout no longer resolves to: the scene is not shown as today's
    sub["resolved_params"]["photos-alone"]["surface.photo_mask_vote"] = 0.5
    (tmp_path / "scan24" / "2026-11-29-photos-alone.json").write_text(json.dumps(sub))
    stale = results_md.results_markdown(tmp_path, tmp_path)
    assert "surface.photo_mask_vote (photos-alone)" in stale and "| scan24 |" not in stale
