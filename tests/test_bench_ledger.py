"""The held-out benchmark's ledger (bench/bench_scenes.py): a call that re-runs some
(scene, method) pairs replaces exactly those rows and keeps the others with their own
commit, machine and load, so a table never mixes figures without saying where each came from."""

import json

from bench_scripts import REPO, load_bench_script


def _bench():
    return load_bench_script("bench_scenes")


def _row(scene, method, psnr, commit):
    return {"scene": scene, "role": "held out", "method": method, "psnr": psnr, "commit": commit,
            "machine": "2 cores, CPU X", "load": 1.0, "seconds": 100.0}


def test_merge_replaces_only_the_rows_that_were_run_and_keeps_the_order():
    bench = _bench()
    old = [_row("thin", "train_nerf", 36.0, "aaa"), _row("thin", "volsdf", 18.0, "aaa"),
           _row("above", "gs_train", 37.0, "bbb"), _row("above", "volsdf", 28.0, "bbb")]
    new = [_row("above", "volsdf", 30.5, "ccc"), _row("thin", "volsdf", 25.0, "ccc"),
           _row("dev", "volsdf", 33.0, "ccc")]
    rows = bench.merge_rows(old, new)
    got = [(r["scene"], r["method"], r["psnr"], r["commit"]) for r in rows]
    assert got == [("thin", "train_nerf", 36.0, "aaa"), ("thin", "volsdf", 25.0, "ccc"),
                   ("above", "gs_train", 37.0, "bbb"), ("above", "volsdf", 30.5, "ccc"),
                   ("dev", "volsdf", 33.0, "ccc")]
    assert bench.merge_rows([], new) == sorted(new, key=lambda r: ["above", "thin", "dev"].index(r["scene"]))


def test_table_names_each_rows_commit_and_the_committed_ledger_is_complete():
    bench = _bench()
    line = bench.table([_row("above", "volsdf", 25.0, "ccc")]).splitlines()[-1]
    assert line.startswith("| above | held out | volsdf | 25.00 |") and line.endswith("| ccc, 2 cores, CPU X, 1.0 |")
    copied = {**_row("thin", "gs_train", 38.0, "ddd"), "load": 2.0, "transcribed_from_table": True}
    assert bench.table([copied]).splitlines()[-1].endswith("| ddd, 2 cores, CPU X, about 2.0 (from the older table) |")
    ledger = json.loads((REPO / "docs" / "benchmark_scenes.json").read_text())
    assert all(r.get("commit") and r.get("machine") for r in ledger)
    doc = (REPO / "docs" / "benchmark_scenes.md").read_text()
    for r in ledger:                       # the markdown table is the ledger, row for row
        assert bench.table([r]).splitlines()[-1] in doc


def test_a_scene_a_methods_choice_looked_at_is_not_called_held_out_for_it(tmp_path):
    """volsdf's mask loss weight was chosen after reading thin: thin's volsdf row says diagnosis, the
    other methods' rows on thin stay held out; --render-only rewrites the table from the ledger
    and keeps the section's 'Last call' sentence."""
    bench = _bench()
    rows = [_row("thin", "volsdf", 25.0, "ccc"), _row("thin", "gs_train", 38.0, "ccc")]
    lines = bench.table(rows).splitlines()[-2:]
    assert lines[0].startswith("| thin | diagnosis") and lines[1].startswith("| thin | held out | gs_train |")
    doc = tmp_path / "bench.md"
    doc.write_text("intro\n" + bench.section_text("Last call: `python bench/bench_scenes.py --methods volsdf` (2 cores).",
                                                   "bench.json", rows[1:]) + "\noutro\n")
    (tmp_path / "bench.json").write_text(json.dumps(rows))
    bench.render_from_ledger(doc)
    text = doc.read_text()
    assert text.startswith("intro\n") and text.endswith("\noutro\n") and "--methods volsdf` (2 cores)." in text
    assert "| thin | diagnosis" in text and (tmp_path / "bench.png").is_file()


def test_a_row_run_with_overrides_says_it_is_not_the_defaults():
    row = {**_row("above", "gs_train", 30.0, "eee"), "overrides": ["iters=10"]}
    assert "| gs_train (iters=10: not the defaults) |" in _bench().table([row])


def test_a_volsdf_row_names_the_density_its_cameras_chose():
    bench = _bench()
    assert "| volsdf (NeuS) |" in bench.table([{**_row("thin", "volsdf", 33.0, "fff"), "density": "neus"}])
    assert "| volsdf (VolSDF) |" in bench.table([{**_row("above", "volsdf", 31.0, "fff"), "density": "volsdf"}])
    assert "| volsdf |" in bench.table([_row("above", "volsdf", 31.0, "ggg")])     # rows measured before the choice
