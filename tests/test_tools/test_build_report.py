"""tools/results/build_report.py: the results folders rebuild byte for byte; --baseline: a folder of
one recipe's JSGS runs gets the other folder's gsplat runs of the same cells and the clean runs of the same
scenes and budgets, with their settings, and nothing else; a folder of scene-sized (auto) budgets names
what auto was and JSGS's gc_every, and refuses the auto runs of two rules; configs.json against
jsgs/schemas/configs.schema.json: the committed ones, freshly written ones, and broken ones refused in one
line naming the file."""

from __future__ import annotations

import copy
import csv
import json
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import load_benchmark

from jsgs.bench.results import read_csv, write_csv

br = load_benchmark("build_report", "tools/results")
ROOT = Path(__file__).resolve().parents[2]
#: committed configs.json entries, the templates of the runs' config.json here (complete, valid settings)
_TEMPLATES = json.loads((ROOT / "docs" / "results" / "operating_point" / "configs.json").read_text())


def _run_doc(method: str, cap: int, opts: dict | None = None, ppg: int | None = None) -> dict:
    """A run's config.json as build_report reads it: a committed run's settings, versions and command with
    ``method`` (gsplat, else a JSGS variant with method options ``opts``) and the budget ``cap``; for an auto
    run (``ppg``: the rule's pixels per Gaussian) a committed ``derived.budget`` choosing ``cap``."""
    trained = "gsplat" if method == "gsplat" else "jsgs"
    tpl = next(v for _, v in sorted(_TEMPLATES.items()) if v["settings"]["method"] == trained)
    doc = copy.deepcopy({k: tpl[k] for k in ("settings", "versions", "command")})
    doc["settings"]["strategy"]["cap_max"] = cap
    if trained == "jsgs":
        doc["settings"]["method_options"] = dict(opts or {})
    if ppg is not None:
        rule = next(v["derived"]["budget"] for _, v in sorted(_TEMPLATES.items()) if "derived" in v)
        doc["derived"] = {"budget": {**rule, "cap_max": cap, "pixels_per_gaussian": ppg}}
    return doc


def _row(scene: str, schedule: str, method: str, seed: int, lpips: float, budget: int = 100000) -> dict:
    return {
        "scene": scene, "schedule": schedule, "method": method, "seed": seed, "strategy": "mcmc",
        "budget": budget, "step": 10000, "psnr": 25.0, "ssim": 0.9, "lpips": lpips, "num_gaussians": budget,
        "train_seconds": 100.0, "time_per_iteration_s": 0.01,
    }  # fmt: skip


def test_baseline_brings_the_cells_gsplat_and_clean_runs(tmp_path: Path) -> None:
    base, bench, target = tmp_path / "default", tmp_path / "bench", tmp_path / "variant"
    base.mkdir(), bench.mkdir()
    rows = [_row(sc, sch, m, s, 0.2) for sc in ("a", "b") for sch in ("uniform", "descending")
            for m in ("gsplat", "jsgs") for s in (0, 1)]  # fmt: skip
    rows += [_row(sc, "clean", "gsplat", s, 0.1) for sc in ("a", "b") for s in (0, 1)]
    rows += [_row("a", "uniform", "gsplat", 0, 0.3, budget=300000)]  # another budget: not brought
    write_csv(rows, base / "results.csv")
    (base / "configs.json").write_text(json.dumps({br.run_key(r): _run_doc(r["method"], r["budget"])
                                                   for r in rows}))  # fmt: skip
    # the bench trained one recipe on scene a, uniform, seeds 0-1
    write_csv([_row("a", "uniform", "jsgs", s, 0.15) for s in (0, 1)], bench / "results.csv")
    br.main(target, [bench], "auto", base)
    got = read_csv(target / "results.csv")
    cells = sorted({(r["scene"], r["schedule"], r["method"], int(r["budget"])) for r in got})
    assert cells == [("a", "clean", "gsplat", 100000), ("a", "uniform", "gsplat", 100000),
                     ("a", "uniform", "jsgs", 100000)]  # fmt: skip
    assert sorted(float(r["lpips"]) for r in got if r["method"] == "jsgs") == [0.15, 0.15]  # the bench's
    assert len(got) == 6
    configs = json.loads((target / "configs.json").read_text())
    want = {f"a/{sch}/gsplat/mcmc-100000/s{s}" for sch in ("uniform", "clean") for s in (0, 1)}
    assert set(configs) == want
    assert (target / "report.md").is_file()


def _bench(folder: Path, rows: list[dict], caps: dict[tuple[str, str], tuple[int, int | None]]) -> None:
    """A bench folder: ``rows`` and the config.json of each of their runs (``caps``: (method, budget) -> its
    cap_max and, for an auto run, the rule's pixels per Gaussian, else None); JSGS at auto with gc_every 4."""
    folder.mkdir()
    write_csv(rows, folder / "results.csv")
    for r in rows:
        cap, ppg = caps[(r["method"], str(r["budget"]))]
        opts = {"gc_every": 4} if r["method"] == "jsgs" and r["budget"] == "auto" else {}
        doc = _run_doc(r["method"], cap, opts, ppg)
        doc["derived"] = {"device": "cuda", **doc.get("derived", {})}  # configs.json keeps budget alone
        run = folder / "runs" / br.run_key(r)
        run.mkdir(parents=True, exist_ok=True)
        (run / "config.json").write_text(json.dumps(doc))


def _auto_row(method: str, seed: int, cap: int) -> dict:
    return {**_row("a", "gaussian", method, seed, 0.1), "budget": "auto", "num_gaussians": cap}


def test_auto_budgets_are_named_and_two_rules_refused(tmp_path: Path) -> None:
    from jsgs.base.schema import validate

    target = tmp_path / "op"
    new = {
        ("gsplat", "auto"): (184000, 30),
        ("jsgs", "auto"): (184000, 30),
        ("jsgs", "100000"): (100000, None),
    }
    rows = [_auto_row(m, s, 184000) for m in ("gsplat", "jsgs") for s in (0, 1)]
    _bench(tmp_path / "new", [*rows, _row("a", "gaussian", "jsgs", 1, 0.1)], new)
    br.main(target, [tmp_path / "new"])
    report = (target / "report.md").read_text()
    rule = (
        "`auto` (`--cap-max auto`): a 184,000 Gaussians, the rule's choice at 30 training pixels per Gaussian"
    )
    assert rule in report
    gc = "Controller in its 3 runs: gc_every 1 in 1 (budgets 100,000); gc_every 4 in 2 (budgets auto)."
    assert gc in report
    configs = json.loads((target / "configs.json").read_text())
    validate(configs, "configs", "configs.json")
    recorded = configs["a/gaussian/jsgs/mcmc-auto/s0"]["derived"]
    assert recorded == {"budget": _run_doc("jsgs", 184000, ppg=30)["derived"]["budget"]}
    assert recorded["budget"]["cap_max"] == 184000 and recorded["budget"]["pixels_per_gaussian"] == 30
    assert "derived" not in configs["a/gaussian/jsgs/mcmc-100000/s1"]
    # seed 2 trained under another rule (552,000 for the same scene): refused, the folder left as it was
    before = {p.name: p.read_bytes() for p in target.iterdir() if p.is_file()}
    old = {("gsplat", "auto"): (552000, 10), ("jsgs", "auto"): (552000, 10)}
    _bench(tmp_path / "old", [_auto_row(m, 2, 552000) for m in ("gsplat", "jsgs")], old)
    refusal = (
        r"^build_report.py: a: its auto runs trained at different budgets \(184,000, 552,000\): gather each "
    )
    with pytest.raises(SystemExit, match=refusal + "rule's runs into a folder of its own$"):
        br.main(target, [tmp_path / "old"])
    assert {p.name: p.read_bytes() for p in target.iterdir() if p.is_file()} == before


def test_refuses_results_without_budget_columns(tmp_path: Path) -> None:
    old = tmp_path / "old"
    old.mkdir()
    # a results.csv from before the strategy and budget columns (write_csv would add them, empty)
    row = _row("a", "gaussian", "gsplat", 0, 0.2)
    row = {k: v for k, v in row.items() if k not in ("strategy", "budget")}
    with (old / "results.csv").open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(row))
        w.writeheader()
        w.writerow(row)
    with pytest.raises(SystemExit, match=r"old/results.csv: no strategy and budget columns; it rebuilds"):
        br.main(old, [])
    # nothing written into the folder it refused
    assert sorted(p.name for p in old.iterdir()) == ["results.csv"]


# Every equal-budget results folder rebuilds (the 17 take about 15 s on 2 cores); a representative few are
# tested, one per way the tables pick their step: the last step (operating_point, double), a fixed step
# (captures, --step 7000) and each scene's last common evaluation (levers/nogc, --step auto).
REBUILT = [
    ("operating_point", None),
    ("double", None),
    ("budget/captures", 7000),
    ("budget/levers/nogc", "auto"),
]


@pytest.mark.parametrize(("folder", "step"), REBUILT, ids=[f for f, _ in REBUILT])
def test_a_results_folder_rebuilds_byte_for_byte(tmp_path: Path, folder: str, step: int | str | None) -> None:
    """A results folder is what the bench's report code makes of its own results.csv and configs.json (with
    the step its tables name): report.md, results.csv and configs.json byte for byte, the same plots (their
    pixels depend on the matplotlib version, so only their names are compared)."""
    import shutil

    committed = Path(__file__).resolve().parents[2] / "docs" / "results" / folder
    target = tmp_path / committed.name
    shutil.copytree(committed, target)
    shutil.rmtree(target / "plots")
    (target / "report.md").unlink()  # made again from results.csv and configs.json, which it rewrites
    br.main(target, [], step)
    for name in ("report.md", "results.csv", "configs.json"):
        assert (target / name).read_bytes() == (committed / name).read_bytes(), name
    assert sorted(p.name for p in (target / "plots").iterdir()) == sorted(
        p.name for p in (committed / "plots").iterdir())  # fmt: skip


def _views_bench(folder: Path, scene: str, psnr: float) -> None:
    """A bench of gsplat and JSGS on ``scene`` (seed 0) whose runs' metrics.json hold two test views each,
    JSGS ``psnr`` dB above gsplat on both."""
    rows = [_row(scene, "gaussian", m, 0, 0.2) for m in ("gsplat", "jsgs")]
    write_csv(rows, folder / "results.csv")
    for r in rows:
        run = folder / "runs" / br.run_key(r)
        run.mkdir(parents=True)
        up = psnr if r["method"] == "jsgs" else 0.0
        views = [{"name": f"v{i}", "psnr": 25.0 + i + up, "ssim": 0.9, "lpips": 0.2} for i in range(2)]
        (run / "metrics.json").write_text(json.dumps({"evals": [{"step": 10000, "views": views}]}))


def test_gathers_keep_every_runs_views(tmp_path: Path) -> None:
    """Two gathers into one folder: views.json holds the runs of both (the run folders stay behind), the
    report's per-view table has both scenes, and a rebuild without benches gives the same report."""
    from jsgs.base.schema import validate

    target, first, second = tmp_path / "op", tmp_path / "b1", tmp_path / "b2"
    _views_bench(first, "a", 1.0)
    _views_bench(second, "b", -1.0)
    br.main(target, [first])
    br.main(target, [second])
    doc = json.loads((target / "views.json").read_text())
    validate(doc, "views", "views.json")
    assert sorted(doc["runs"]) == sorted(br.run_key(r) for r in read_csv(target / "results.csv"))
    assert len(doc["runs"]) == 4
    report = (target / "report.md").read_text()
    section = report.split("## Per test view")[1].split("\n## ")[0]
    per_view = [ln for ln in section.splitlines() if ln.startswith(("| a |", "| b |"))]
    assert [ln.split("|")[8].strip() for ln in per_view] == ["2/2", "0/2"]
    (target / "report.md").unlink()
    br.main(target, [])
    assert (target / "report.md").read_text() == report


def test_replaced_runs_without_views_drop_their_old_views(tmp_path: Path) -> None:
    """A gather whose bench replaces every run with runs that have no per-view metrics (their metrics.json
    not readable yet): views.json no longer holds the replaced runs' views, and the report says the pair has
    none (the section's skip line) instead of showing the old runs'."""
    target, first, second = tmp_path / "op", tmp_path / "b1", tmp_path / "b2"
    _views_bench(first, "a", 1.0)
    _views_bench(second, "a", -1.0)
    for m in (second / "runs").glob("*/*/*/*/*/metrics.json"):
        m.write_text("{")  # a run still writing it
    br.main(target, [first])
    br.main(target, [second])
    doc = json.loads((target / "views.json").read_text())
    assert doc["runs"] == {}
    section = (target / "report.md").read_text().split("## Per test view")[1].split("\n## ")[0]
    assert "Skipped: no per-view metrics here" in section and "| a |" not in section


def test_a_run_gathered_again_keeps_no_views_of_the_baselines(tmp_path: Path) -> None:
    """--baseline: the base's views come with the runs taken from it; a run the gather brings again has
    its gather's views alone, none where its metrics.json is not readable (not the base's old ones)."""
    base, first, again = tmp_path / "default", tmp_path / "b1", tmp_path / "b2"
    _views_bench(first, "a", 1.0)
    br.main(base, [first])
    gsplat, jsgs = (br.run_key(_row("a", "gaussian", m, 0, 0.2)) for m in ("gsplat", "jsgs"))
    assert sorted(json.loads((base / "views.json").read_text())["runs"]) == [gsplat, jsgs]
    _views_bench(again, "a", -1.0)
    (again / "runs" / gsplat / "metrics.json").write_text("{")  # a run still writing it
    only_jsgs = tmp_path / "b3"
    _views_bench(only_jsgs, "a", -1.0)
    write_csv([r for r in read_csv(only_jsgs / "results.csv") if r["method"] == "jsgs"],
              only_jsgs / "results.csv")  # fmt: skip
    for target, bench in ((tmp_path / "t1", only_jsgs), (tmp_path / "t2", again)):
        br.main(target, [bench], None, base)
        assert sorted(r["method"] for r in read_csv(target / "results.csv")) == ["gsplat", "jsgs"]
        runs = json.loads((target / "views.json").read_text())["runs"]
        assert sorted(runs) == ([gsplat, jsgs] if bench is only_jsgs else [jsgs])
        base_runs = json.loads((base / "views.json").read_text())["runs"]
        if bench is only_jsgs:
            assert runs[gsplat] == base_runs[gsplat]
        assert runs[jsgs] != base_runs[jsgs]  # the gather's


def _config(run: Path, cap: int) -> None:
    """A config.json in the run folder ``run`` (``runs/<scene>/<schedule>/<method>/...``; its settings name
    ``cap``)."""
    (run / "config.json").write_text(json.dumps(_run_doc(run.parts[-3], cap)))


def test_replaced_runs_without_a_config_drop_their_old_settings(tmp_path: Path) -> None:
    """A gather that replaces runs whose config.json is missing or not readable: configs.json no longer
    holds the replaced runs' old settings (those runs have none), and the report still builds."""
    target, first, second = tmp_path / "op", tmp_path / "b1", tmp_path / "b2"
    _views_bench(first, "a", 1.0)
    _views_bench(second, "a", -1.0)
    gsplat, jsgs = (br.run_key(_row("a", "gaussian", m, 0, 0.2)) for m in ("gsplat", "jsgs"))
    for run in (first / "runs").glob("*/*/*/*/*"):
        _config(run, 1)
    br.main(target, [first])
    assert sorted(json.loads((target / "configs.json").read_text())) == [gsplat, jsgs]
    _config(second / "runs" / jsgs, 2)
    br.main(target, [second])  # gsplat's run brought again without a config.json
    configs = json.loads((target / "configs.json").read_text())
    assert sorted(configs) == [jsgs] and configs[jsgs]["settings"]["strategy"]["cap_max"] == 2
    third = tmp_path / "b3"
    _views_bench(third, "a", 0.5)
    (third / "runs" / jsgs / "config.json").write_text("{")  # not readable
    br.main(target, [third])
    assert json.loads((target / "configs.json").read_text()) == {}
    assert sorted(r["method"] for r in read_csv(target / "results.csv")) == ["gsplat", "jsgs"]
    assert (target / "report.md").is_file()


def test_a_run_gathered_again_keeps_no_settings_of_the_baselines(tmp_path: Path) -> None:
    """--baseline: the base's settings come with the runs taken from it; a run the gather brings again has
    its gather's settings alone, none where it brings no readable config.json (not the base's old ones)."""
    base, first, again = tmp_path / "default", tmp_path / "b1", tmp_path / "b2"
    _views_bench(first, "a", 1.0)
    for run in (first / "runs").glob("*/*/*/*/*"):
        _config(run, 1)
    br.main(base, [first])
    gsplat, jsgs = (br.run_key(_row("a", "gaussian", m, 0, 0.2)) for m in ("gsplat", "jsgs"))
    base_cfg = json.loads((base / "configs.json").read_text())
    assert sorted(base_cfg) == [gsplat, jsgs]
    _views_bench(again, "a", -1.0)
    _config(again / "runs" / jsgs, 2)  # gsplat's run brought again without one
    only_jsgs = tmp_path / "b3"
    _views_bench(only_jsgs, "a", -1.0)
    _config(only_jsgs / "runs" / jsgs, 2)
    write_csv([r for r in read_csv(only_jsgs / "results.csv") if r["method"] == "jsgs"],
              only_jsgs / "results.csv")  # fmt: skip
    for target, bench in ((tmp_path / "t1", only_jsgs), (tmp_path / "t2", again)):
        br.main(target, [bench], None, base)
        assert sorted(r["method"] for r in read_csv(target / "results.csv")) == ["gsplat", "jsgs"]
        configs = json.loads((target / "configs.json").read_text())
        assert sorted(configs) == ([gsplat, jsgs] if bench is only_jsgs else [jsgs])
        if bench is only_jsgs:
            assert configs[gsplat] == base_cfg[gsplat]
        assert configs[jsgs]["settings"]["strategy"]["cap_max"] == 2  # the gather's


def test_auto_runs_without_settings_are_named(tmp_path: Path) -> None:
    """A folder of auto budgets where some runs have no config.json: the header names what it knows from
    the others, says so, and lists the runs without recorded settings instead of leaving them out."""
    caps = {("gsplat", "auto"): (184000, 30), ("jsgs", "auto"): (184000, 30)}
    rows = [_auto_row(m, s, 184000) for m in ("gsplat", "jsgs") for s in (0, 1)]
    _bench(tmp_path / "new", rows, caps)
    missing = [br.run_key(_auto_row(m, 1, 184000)) for m in ("gsplat", "jsgs")]
    for run in missing:
        (tmp_path / "new" / "runs" / run / "config.json").unlink()
    br.main(tmp_path / "op", [tmp_path / "new"])
    report = (tmp_path / "op" / "report.md").read_text()
    rule = "a 184,000 Gaussians, the rule's choice at 30 training pixels per Gaussian (not recorded for every"
    assert rule in report
    assert "Controller in its 1 runs with settings recorded: gc_every 4 in 1 (budgets auto)." in report
    listed = f"Runs without recorded settings (no readable config.json): {', '.join(sorted(missing))}."
    assert listed in report and "of every run but those named below in configs.json" in report
    assert sorted(json.loads((tmp_path / "op" / "configs.json").read_text())) == sorted(
        br.run_key(r) for r in rows if br.run_key(r) not in missing)  # fmt: skip


# ---------------------------------------------------------------------------------------------------------
# configs.json and its schema


def test_every_committed_configs_json_is_valid() -> None:
    """Every configs.json of a results folder build_report.py gathers validates as it is committed; the only
    others are beside a results.csv it refuses (the first probes' record in docs/results/budget, keyed by
    run name, from before the bench's strategy and budget columns)."""
    checked, others = [], []
    for path in sorted((ROOT / "docs" / "results").glob("**/configs.json")):
        with (path.parent / "results.csv").open(newline="") as f:
            columns = next(csv.reader(f))
        if {"strategy", "budget"} <= set(columns):
            assert br.read_configs_file(path), path  # raises (one line naming it) where it is not valid
            checked.append(path)
        else:
            with pytest.raises(SystemExit, match="no strategy and budget columns"):
                br.budget_csv(path.parent / "results.csv")
            others.append(path.relative_to(ROOT).as_posix())
    assert len(checked) >= 20 and others == ["docs/results/budget/configs.json"]


def _gathered(tmp_path: Path) -> tuple[Path, dict[str, bytes]]:
    """A results folder gathered from one bench of gsplat and JSGS with their config.json, and its files."""
    target, bench = tmp_path / "op", tmp_path / "b1"
    _views_bench(bench, "a", 1.0)
    for run in (bench / "runs").glob("*/*/*/*/*"):
        _config(run, 100000)
    br.main(target, [bench])
    return target, {p.name: p.read_bytes() for p in target.iterdir() if p.is_file()}


def test_configs_json_written_is_valid_and_broken_ones_refused(tmp_path: Path) -> None:
    """The configs.json a gather writes validates; one that is not JSON, has a key that is not a run key, a
    setting this version does not know or a run without versions is refused in one line naming it (the
    schema's references into config.schema.json hold), and nothing in the folder is written."""
    from jsgs.base.errors import JsgsError
    from jsgs.base.schema import validate

    target, files = _gathered(tmp_path)
    good = json.loads(files["configs.json"])
    validate(good, "configs", "configs.json")
    assert len(good) == 2
    run = next(iter(good))
    broken = {
        "not JSON": (b'{"a": ', "not JSON: Expecting value"),
        "not a run key": ({"a/gaussian/gsplat/s0": good[run]}, "does not match"),
        "unknown setting": ({run: {**good[run], "settings": {**good[run]["settings"], "speedy": True}}},
                            f"at {run}/settings: Additional properties are not allowed"),
        "no versions": ({run: {k: v for k, v in good[run].items() if k != "versions"}},
                        f"at {run}: 'versions' is a required property"),
    }  # fmt: skip
    for why, (doc, says) in broken.items():
        data = doc if isinstance(doc, bytes) else json.dumps(doc).encode()
        (target / "configs.json").write_bytes(data)
        (target / "report.md").unlink()
        with pytest.raises(JsgsError) as e:
            br.main(target, [])
        msg = str(e.value)
        assert msg.startswith(f"{target / 'configs.json'}: ") and says in msg and "\n" not in msg, why
        assert not (target / "report.md").exists(), why
        assert (target / "results.csv").read_bytes() == files["results.csv"], why
        (target / "report.md").write_bytes(files["report.md"])


def test_a_runs_config_json_that_is_no_valid_entry_is_named(tmp_path: Path) -> None:
    """A bench run whose config.json reads but holds a setting this version does not know stops the gather
    in one line naming that config.json, nothing written; from the command line: that line, exit status 1,
    no traceback."""
    target, files = _gathered(tmp_path)
    bench = tmp_path / "b2"
    _views_bench(bench, "a", -1.0)
    runs = sorted((bench / "runs").glob("*/*/*/*/*"))
    for run in runs:
        _config(run, 100000)
    doc = json.loads((runs[0] / "config.json").read_text())
    doc["settings"]["strategy"]["speedy"] = True
    (runs[0] / "config.json").write_text(json.dumps(doc))
    script = ROOT / "tools" / "results" / "build_report.py"
    r = subprocess.run([sys.executable, str(script), str(target), str(bench)], capture_output=True, text=True)
    assert r.returncode == 1 and r.stdout == ""
    err = r.stderr.strip()
    assert "\n" not in err and err.startswith(f"build_report.py: {runs[0] / 'config.json'} (as an entry of ")
    assert "settings/strategy: Additional properties are not allowed ('speedy' was unexpected)" in err
    assert {p.name: p.read_bytes() for p in target.iterdir() if p.is_file()} == files


def test_settings_recorded_under_an_earlier_name_gather(tmp_path: Path) -> None:
    """A bench run's config.json (and a results folder's configs.json) written when ``speed.exchange`` was
    ``auto`` reads as jsgs reads it (``gsplat``, :func:`jsgs.train.config.current_values`): the gather
    goes through and configs.json records today's value, valid against its schema."""
    from jsgs.base.schema import validate

    target, bench = tmp_path / "op", tmp_path / "b1"
    _views_bench(bench, "a", 1.0)
    runs = sorted((bench / "runs").glob("*/*/*/*/*"))
    for run in runs:
        doc = _run_doc(run.parts[-3], 100000)
        doc["settings"]["speed"] = {**doc["settings"].get("speed", {}), "exchange": "auto"}
        (run / "config.json").write_text(json.dumps(doc))
    br.main(target, [bench])
    configs = json.loads((target / "configs.json").read_text())
    validate(configs, "configs", "configs.json")
    assert len(configs) == len(runs) == 2
    assert {c["settings"]["speed"]["exchange"] for c in configs.values()} == {"gsplat"}
    # a configs.json gathered before: its old value reads too
    old = {k: {**v, "settings": {**v["settings"], "speed": {"exchange": "auto"}}} for k, v in configs.items()}
    (target / "configs.json").write_text(json.dumps(old))
    back = br.read_configs_file(target / "configs.json")
    assert {c["settings"]["speed"]["exchange"] for c in back.values()} == {"gsplat"}


def test_runs_written_before_a_setting_existed_gather(tmp_path: Path) -> None:
    """A bench run's config.json written before ``speed`` and ``checkpoint_keep`` existed gathers (read as
    jsgs reads it, :func:`jsgs.train.config.settings_of_today`); configs.json keeps its settings as recorded
    and reads back; one lacking a setting whose earlier value is not known stops the gather in one line
    naming that config.json, nothing written."""
    from jsgs.base.errors import JsgsError

    target, bench = tmp_path / "op", tmp_path / "b1"
    _views_bench(bench, "a", 1.0)
    runs = sorted((bench / "runs").glob("*/*/*/*/*"))
    for run in runs:
        doc = _run_doc(run.parts[-3], 100000)
        del doc["settings"]["speed"], doc["settings"]["checkpoint_keep"]
        (run / "config.json").write_text(json.dumps(doc))
    br.main(target, [bench])
    configs = json.loads((target / "configs.json").read_text())
    assert len(configs) == len(runs) == 2
    assert all("speed" not in c["settings"] for c in configs.values())
    assert br.read_configs_file(target / "configs.json") == configs
    files = {p.name: p.read_bytes() for p in target.iterdir() if p.is_file()}
    again = tmp_path / "b2"
    _views_bench(again, "a", -1.0)
    for run in sorted((again / "runs").glob("*/*/*/*/*")):
        doc = _run_doc(run.parts[-3], 100000)
        del doc["settings"]["loss"]["ssim_lambda"]
        (run / "config.json").write_text(json.dumps(doc))
    says = r"config.json \(as an entry of configs.json\) \(.*\): lacks the setting loss.ssim_lambda"
    with pytest.raises(JsgsError, match=says):
        br.main(target, [again])
    assert {p.name: p.read_bytes() for p in target.iterdir() if p.is_file()} == files


def test_views_that_would_not_be_valid_stop_the_gather_before_anything_is_written(tmp_path: Path) -> None:
    """A bench run whose metrics.json reads but whose views would not make a valid views.json (an
    evaluation at step 0) stops the gather in one line naming views.json, and the folder's files are left
    as they were (results.csv and configs.json not rewritten before the refusal)."""
    from jsgs.base.errors import JsgsError

    target, files = _gathered(tmp_path)
    bench = tmp_path / "b2"
    _views_bench(bench, "a", -1.0)
    write_csv([_row("a", "gaussian", m, 0, 0.3) for m in ("gsplat", "jsgs")], bench / "results.csv")
    for run in sorted((bench / "runs").glob("*/*/*/*/*")):
        _config(run, 2)
        metrics = json.loads((run / "metrics.json").read_text())
        metrics["evals"][0]["step"] = 0
        (run / "metrics.json").write_text(json.dumps(metrics))
    with pytest.raises(JsgsError) as e:
        br.main(target, [bench])
    assert str(e.value).startswith(f"{target / 'views.json'}: ") and "\n" not in str(e.value)
    assert {p.name: p.read_bytes() for p in target.iterdir() if p.is_file()} == files
