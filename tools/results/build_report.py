"""Rebuild an equal-budget results folder's ``report.md`` (and plots) from its ``results.csv`` with the
bench's own report code, first adding the runs of bench folders brought back from GPU calls.

    .venv/bin/python tools/results/build_report.py docs/results/budget/confirm .res/flower .res/b100
    .venv/bin/python tools/results/build_report.py docs/results/double .res/double
    .venv/bin/python tools/results/build_report.py --step 7000 docs/results/budget/captures .res/captures

A bench folder (``jsgs bench --out``, or the contents of a ``$OUT/*.tgz`` of ``tools/campaigns/confirm.sh``
or ``double.sh``) contributes its results.csv rows and its runs' config.json (into ``configs.json``: settings,
versions, command and, for the scene-sized budget, ``derived.budget``, the rule's inputs and choice) and
their metrics.json's per-view metrics (into ``views.json``, for report.md's "Per test view"); its runs replace
the rows, settings and views of the same scene, schedule, method, budget and seed (a run brought again has
its folder's settings and views alone, none where its folder has none: report.md's header lists the runs
without a readable config.json). Where results.csv holds ``auto`` rows, report.md's header names what
``auto`` was per scene and JSGS's ``gc_every`` per budget (from configs.json), and the auto runs of one scene
that trained at different budgets (two versions of the rule) stop it with one line: gather those into
folders of their own. configs.json (schema ``jsgs/schemas/configs.schema.json``) is checked when read and
before it is written: one that is not valid, or a run's config.json that would not be a valid entry, stops
it with one line naming the file, nothing written; so do views that would not make a valid views.json. The
tables are computed at the last step (10,000), or at ``--step N`` (for runs that all stopped earlier); runs
that stopped before it are listed as such; ``--step auto`` compares each scene, at each budget, at the last
evaluation every one of its runs reached (:func:`jsgs.bench.budget.common_steps`).

    .venv/bin/python tools/results/build_report.py --step auto docs/results/budget/default \
        .res/b100 .res/captures

``--baseline FOLDER`` also copies, from another results folder, the runs that are not JSGS (gsplat, and the
clean runs of every scene and budget concerned) for the cells the bench folders bring, with their settings
and per-view metrics (a run the bench folders bring again has their settings and views alone): a folder of
JSGS runs of one recipe then holds its own comparison (what ``blockiness/`` and ``levers/`` hold).

    .venv/bin/python tools/results/build_report.py --step auto --baseline docs/results/budget/default \
        docs/results/budget/blockiness/b0.5 .res/cb5 .res/lb5
"""

from __future__ import annotations

import csv
import dataclasses
import json
import sys
from collections import defaultdict
from pathlib import Path

from jsgs.base.errors import JsgsError
from jsgs.base.io import write_json_atomic
from jsgs.base.limits import read_json
from jsgs.base.schema import validate
from jsgs.bench import per_view
from jsgs.bench.budget import common_steps
from jsgs.bench.markdown import write_report
from jsgs.bench.results import read_csv, write_csv
from jsgs.method.options import JsgsOptions
from jsgs.train.config import current_values, settings_of_today


def key(r: dict) -> tuple:
    return (r["scene"], r["schedule"], r["method"], str(r["budget"]), str(r["seed"]))


def run_key(r: dict) -> str:
    """The run's folder under ``runs/`` (and its key in configs.json and views.json) of a results.csv row."""
    return per_view.run_key(r["scene"], r["schedule"], r["method"], r["budget"], r["seed"])


def baseline(folder: Path, cells: set[tuple[str, str, str]]) -> tuple[list[dict], dict]:
    """``folder``'s rows that are not JSGS for the (scene, schedule, budget) ``cells``, and the clean runs
    of their scenes and budgets, with those runs' settings from its configs.json."""
    scenes = {(s, b) for s, _, b in cells}
    rows = [r for r in budget_csv(folder / "results.csv")
            if r["strategy"] == "mcmc" and r["method"] != "jsgs"
            and ((r["scene"], r["schedule"], str(r["budget"])) in cells
                 or (r["schedule"] == "clean" and (r["scene"], str(r["budget"])) in scenes))]  # fmt: skip
    known = read_configs_file(folder / CONFIGS_FILE)
    return rows, {k: known[k] for k in {run_key(r) for r in rows} if k in known}


#: the runs' settings of a results folder, schema ``jsgs/schemas/configs.schema.json``
CONFIGS_FILE = "configs.json"


def read_configs_file(path: Path) -> dict[str, dict]:
    """A results folder's configs.json (none there: no runs); JsgsError (one line naming ``path``) where it is
    not one."""
    if not path.is_file():
        return {}
    doc = read_json(path, "JSON")
    if isinstance(doc, dict):  # settings values recorded under an earlier name read as today's
        doc = {k: _current(v) for k, v in doc.items()}
    validate_configs(doc, str(path))
    return doc


def _current(entry: object) -> object:
    """A configs.json entry (or a run's config.json) with its settings' values recorded under an earlier
    name replaced by today's (:func:`jsgs.train.config.current_values`, as jsgs reads a run's config.json:
    ``speed.exchange: auto`` is ``gsplat``); anything else as it is."""
    if not (isinstance(entry, dict) and isinstance(entry.get("settings"), dict)):
        return entry
    return {**entry, "settings": current_values(entry["settings"])}


def validate_configs(configs: object, where: str) -> None:
    """``configs`` (a configs.json map) checked against configs.schema.json with each entry's settings as jsgs
    reads a run's config.json (:func:`jsgs.train.config.settings_of_today`: a run's config.json written before
    a setting existed lacks it and is read with the value that does what that version did); the settings
    are kept as the run recorded them. JsgsError (one line naming ``where``) where not valid."""
    if isinstance(configs, dict):
        configs = {k: _read_as_today(v, f"{where} ({k})") for k, v in configs.items()}
    validate(configs, "configs", where)


def _read_as_today(entry: object, where: str) -> object:
    if not (isinstance(entry, dict) and isinstance(entry.get("settings"), dict)):
        return entry
    return {**entry, "settings": settings_of_today(entry["settings"], where)[0]}


def run_config(doc: dict) -> dict:
    """What configs.json keeps of a run's config.json: settings, versions, command and, where the run chose
    its budget from the scene (``--cap-max auto``), the rule's inputs and choice (``derived.budget``); the
    settings with today's names for values recorded under earlier ones (:func:`_current`)."""
    out = _current({k: doc[k] for k in ("settings", "versions", "command")})
    rule = doc.get("derived", {}).get("budget")
    if rule is not None:
        out["derived"] = {"budget": rule}
    return out


def read_configs(runs_dir: Path) -> dict[str, dict]:
    """configs.json's entry (:func:`run_config`) of every equal-budget run under ``runs_dir`` (``runs/``), by
    run key; a config.json that cannot be read is left out (that run has no settings), as
    :func:`jsgs.bench.per_view.read_runs` leaves out a metrics.json. JsgsError (one line naming it) for one
    that reads but whose entry would not be valid in configs.json (a setting this version does not know)."""
    out: dict[str, dict] = {}
    for p in sorted(runs_dir.glob("*/*/*/mcmc-*/s*/config.json")):
        run = p.parent.relative_to(runs_dir).as_posix()
        try:
            entry = run_config(json.loads(p.read_text()))
        except (OSError, ValueError, KeyError, TypeError, AttributeError):
            continue
        validate_configs({run: entry}, f"{p} (as an entry of configs.json)")
        out[run] = entry
    return out


def _gc_every(settings: dict) -> int:
    """JSGS's ``gc_every`` in a run's settings (not recorded: the options' default)."""
    default = {f.name: f.default for f in dataclasses.fields(JsgsOptions)}["gc_every"]
    return int(settings.get("method_options", {}).get("gc_every", default))


def _budgets(budgets: set[str]) -> str:
    """Budgets as the tables name them, the fixed ones in order, then ``auto``."""
    order = sorted(budgets, key=lambda b: (not b.isdigit(), int(b) if b.isdigit() else 0))
    return ", ".join(f"{int(b):,}" if b.isdigit() else b for b in order)


def auto_notes(rows: list[dict], configs: dict) -> list[str]:
    """Header lines saying what the ``auto`` budget was per scene (the rule's choice and its pixels per
    Gaussian, from configs.json) and JSGS's ``gc_every`` per budget, of the runs of ``rows`` with settings in
    ``configs``; none without ``auto`` rows. SystemExit (one line) where one scene's auto runs trained at
    different budgets."""
    auto_scenes = {r["scene"] for r in rows if str(r["budget"]) == "auto"}
    if not auto_scenes:
        return []
    caps: dict[str, set[int]] = defaultdict(set)
    ppg: set[int | None] = set()
    gc: dict[int, list[str]] = defaultdict(list)  # gc_every -> the budget of each JSGS run
    runs = {run_key(r) for r in rows}
    for run in runs:
        scene, _, method, budget, _ = run.split("/")
        c = configs.get(run)
        if c is None:  # no settings: for an auto run, its rule's inputs not recorded either
            if budget == "mcmc-auto":
                ppg.add(None)
            continue
        if method == "jsgs":
            gc[_gc_every(c["settings"])].append(budget.removeprefix("mcmc-"))
        if budget == "mcmc-auto" and scene in auto_scenes:
            caps[scene].add(int(c["settings"]["strategy"]["cap_max"]))
            ppg.add(c.get("derived", {}).get("budget", {}).get("pixels_per_gaussian"))
    for scene, v in sorted(caps.items()):
        if len(v) > 1:
            sys.exit(f"build_report.py: {scene}: its auto runs trained at different budgets "
                     f"({', '.join(f'{n:,}' for n in sorted(v))}): gather each rule's runs into a folder of "
                     "its own")  # fmt: skip
    chosen = ", ".join(f"{s} {min(v):,}" for s, v in sorted(caps.items())) or "no run's settings recorded"
    known = sorted(p for p in ppg if p is not None)
    rule = (
        f"at {' / '.join(map(str, known))} training pixels per Gaussian"
        if known
        else "its pixels per Gaussian"
    )
    rule += " (not recorded for every run)" if None in ppg and known else "" if known else " not recorded"
    lines = [f"Budget `auto` (`--cap-max auto`): {chosen} Gaussians, the rule's choice {rule} (each run's "
             "`derived.budget` in configs.json)."]  # fmt: skip
    if gc:
        n = sum(len(v) for v in gc.values())
        parts = "; ".join(
            f"gc_every {k} in {len(v)} (budgets {_budgets(set(v))})" for k, v in sorted(gc.items())
        )
        recorded = "" if runs <= configs.keys() else " with settings recorded"
        lines.append(f"JSGS's Gaussian Controller in its {n} runs{recorded}: {parts}.")
    return lines


def budget_csv(path: Path) -> list[dict]:
    """``path``'s rows; SystemExit (one line) where it is not an equal-budget bench's results.csv (one made
    before the ``strategy`` and ``budget`` columns, e.g. ``paper_protocol/``'s DefaultStrategy runs, or a
    probe's table of other columns, which are not read)."""
    with path.open(newline="") as f:
        columns = next(csv.reader(f), None)
    if columns is not None and not {"strategy", "budget"} <= set(columns):
        sys.exit(f"build_report.py: {path}: no strategy and budget columns; it rebuilds the results of "
                 "`jsgs bench --strategy mcmc` only")  # fmt: skip
    return read_csv(path)


def main(target: Path, folders: list[Path], step: int | str | None = None, base: Path | None = None) -> None:
    csv = target / "results.csv"
    rows = budget_csv(csv) if csv.is_file() else []
    cfg = target / CONFIGS_FILE
    configs = read_configs_file(cfg)
    views = per_view.load(target)
    for f in folders:
        new = [r for r in budget_csv(f / "results.csv") if r["strategy"] == "mcmc"]
        done = {key(r) for r in new}
        rows = [r for r in rows if key(r) not in done] + new
        # a run brought again has its folder's settings and views alone (none where it has none)
        replaced = {run_key(r) for r in new}
        views = {k: v for k, v in views.items() if k not in replaced}
        views.update(per_view.read_runs(f / "runs"))
        configs = {k: v for k, v in configs.items() if k not in replaced}
        configs.update(read_configs(f / "runs"))
    if base is not None:
        cells = {(r["scene"], r["schedule"], str(r["budget"])) for r in rows if r["method"] == "jsgs"}
        extra, extra_cfg = baseline(base, cells)
        have = {key(r) for r in rows}
        taken = [r for r in extra if key(r) not in have]
        rows += taken
        # the base's settings and views of the runs taken from it alone: a run gathered again has only its
        # gather's
        from_base = {run_key(r) for r in taken}
        configs.update({k: v for k, v in extra_cfg.items() if k in from_base})
        views.update({k: v for k, v in per_view.load(base).items() if k in from_base})
    rows.sort(key=lambda r: (*key(r), int(r["step"])))
    kept = {run_key(r) for r in rows}
    configs = {k: v for k, v in configs.items() if k in kept}
    configs = dict(sorted(configs.items()))
    views = {k: v for k, v in views.items() if k in kept}
    # before anything is written: configs.json and views.json checked, the notes (they may refuse)
    validate_configs(configs, str(cfg))
    validate(per_view.to_doc(views), "views", str(target / per_view.VIEWS_FILE))
    notes = auto_notes(rows, configs)
    target.mkdir(parents=True, exist_ok=True)
    write_csv(rows, csv)
    write_json_atomic(cfg, configs)
    if views or (target / per_view.VIEWS_FILE).is_file():  # an earlier gather's, replaced even by none
        per_view.write_file(target / per_view.VIEWS_FILE, views)
    unrecorded = sorted(kept - configs.keys())
    settings = (
        "the settings and versions of every run but those named below"
        if unrecorded
        else "every run's settings and versions"
    )
    header = [
        f"Every equal-budget run of `{target.name}` (`jsgs bench --strategy mcmc`), gathered from the GPU "
        f"calls that ran them by `tools/results/build_report.py`; {settings} in configs.json, every "
        "evaluation in results.csv.",
        *(["", *notes] if notes else []),
        *(
            [f"Runs without recorded settings (no readable config.json): {', '.join(unrecorded)}."]
            if unrecorded
            else []
        ),
    ]
    at: int | dict[tuple[str, int], int] | None = common_steps(rows) if step == "auto" else None
    if isinstance(step, int):
        at = step
    if isinstance(at, dict):
        header.append(
            "Each scene is compared, at each budget, at the last evaluation every one of its runs reached."
        )
    elif at is not None:
        header.append(f"The tables compare step {at:,}, the last evaluation every run reached.")
    print(write_report(rows, target, header, [], budget_step=at))


if __name__ == "__main__":
    args = sys.argv[1:]
    at: int | str | None = None
    base: Path | None = None
    while args[:1] in (["--step"], ["--baseline"]):
        if len(args) < 2:
            sys.exit(f"build_report.py: {args[0]} needs a value")
        if args[0] == "--step":
            if not (args[1].isdigit() or args[1] == "auto"):
                sys.exit("build_report.py: --step needs a step number or auto")
            at = args[1] if args[1] == "auto" else int(args[1])
        else:
            base = Path(args[1])
            if not (base / "results.csv").is_file():
                sys.exit(f"build_report.py: --baseline {base}: no results.csv there")
        args = args[2:]
    if args[:1] in (["-h"], ["--help"]):
        print(__doc__)
        sys.exit(0)
    if not args or any(a.startswith("-") for a in args):
        sys.exit("usage: build_report.py [--step N|auto] [--baseline FOLDER] TARGET [BENCH_FOLDER ...]")
    missing = [a for a in args[1:] if not (Path(a) / "results.csv").is_file()]
    if missing:
        sys.exit(f"build_report.py: {missing[0]}: not a bench folder (no results.csv there)")
    try:
        main(Path(args[0]), [Path(a) for a in args[1:]], at, base)
    except JsgsError as e:
        sys.exit(f"build_report.py: {e}")
