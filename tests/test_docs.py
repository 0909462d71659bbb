"""The documentation as a user meets it: a README of at most 250 lines, links that resolve, no development
history in the docs or in what the project ships, a CLI reference that is the programs' own help, and every
Python name (jsgs.x.y) and command (`jsgs SUBCOMMAND --option`) the docs write down one that exists."""

from __future__ import annotations

import functools
import re
import sys
from collections.abc import Callable
from pathlib import Path

import pytest

from jsgs.base.errors import JsgsError

ROOT = Path(__file__).resolve().parents[1]
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]
# words that narrate the project's history ("session", "issue" or "call" and a number); CHANGELOG.md is exempt
HISTORY = re.compile(r"\b(session|issue|issues|call)s? ?\d", re.IGNORECASE)


def test_readme_is_short() -> None:
    lines = (ROOT / "README.md").read_text().splitlines()
    assert len(lines) <= 250, len(lines)


@pytest.mark.parametrize("page", DOCS, ids=lambda p: str(p.relative_to(ROOT)))
def test_relative_links_resolve(page: Path) -> None:
    text = page.read_text()
    for target in re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", text):
        if "://" in target or target.startswith("mailto:"):
            continue
        assert (page.parent / target).exists(), f"{page.relative_to(ROOT)}: broken link {target}"


def test_no_history_in_docs_or_shipped_files() -> None:
    files = [*DOCS]
    for folder in ("jsgs", "jsgstools", "scripts", "tools", "benchmarks", ".ci"):
        for p in (ROOT / folder).rglob("*"):
            if p.suffix in {".py", ".sh", ".json", ".cu", ".cpp", ".md"} and p.is_file():
                files.append(p)
    files = [p for p in files if "docs/results/paper_protocol/runs" not in str(p)]
    hits = []
    for p in files:
        for i, line in enumerate(p.read_text(errors="replace").splitlines(), 1):
            if HISTORY.search(line):
                hits.append(f"{p.relative_to(ROOT)}:{i}: {line.strip()[:100]}")
    assert not hits, "\n".join(hits[:20])


# words that narrate a change rather than describe the present ("now the default", "previously")
CHANGE_TALK = re.compile(
    r"\b(previously|formerly|used to be|now the default|no longer (?:the default|used|needed|supported)|"
    r"the (?:new|old) defaults?)\b",
    re.IGNORECASE,
)


def test_docs_describe_the_present() -> None:
    """README.md and docs/ say what the code does, not how it changed (CHANGELOG.md holds that)."""
    hits = [
        f"{p.relative_to(ROOT)}:{i}: {line.strip()[:100]}"
        for p in DOCS if "docs/results/paper_protocol/runs" not in str(p)
        for i, line in enumerate(p.read_text().splitlines(), 1) if CHANGE_TALK.search(line)
    ]  # fmt: skip
    assert not hits, "\n".join(hits[:20])
    said = "the colour kernel (now the default) and the flag, previously on; the new defaults"
    assert CHANGE_TALK.findall(said) == ["now the default", "previously", "the new defaults"]
    assert not CHANGE_TALK.search("a downscaled copy no longer holds the grid; the default is used")


def test_cli_reference_is_current() -> None:
    sys.path.insert(0, str(ROOT / "scripts"))
    try:
        import cli_reference
    finally:
        sys.path.pop(0)
    pages = cli_reference.pages()
    on_disk = {p.name: p.read_text() for p in (ROOT / "docs" / "cli").glob("*.md")}
    assert set(on_disk) == set(pages), "run scripts/cli_reference.py"
    for name, text in pages.items():
        assert on_disk[name] == text, f"docs/cli/{name} is stale: run scripts/cli_reference.py"


def test_every_command_help_ends_with_an_example() -> None:
    from click.testing import CliRunner

    from jsgs.cli import main as jsgs_main
    from jsgstools.cli import main as tools_main

    for group, prog in ((jsgs_main, "jsgs"), (tools_main, "jsgstools")):
        for name in group.commands:
            out = CliRunner().invoke(group, [name, "--help"]).output
            tail = out.rstrip().splitlines()[-2:]
            assert tail[0].strip() == "Example:", (name, tail)
            assert tail[1].strip().startswith(f"{prog} {name}"), (name, tail)
            # the example runs as written: its options are the command's, their values ones it takes
            rest = COMMAND.findall(tail[1])[0][2]
            opts = re.findall(r"(?<![\w-])(--[a-z][a-z0-9-]*)", rest)
            assert set(opts) <= _commands()[prog][name] and not _refused_values(tail[1]), (name, tail)


# ---------------------------------------------------------------------------------------------------------
# names and commands in the docs resolve

# a dotted name of this project's code: jsgs.x.y or jsgstools.x (not part of a path, a URL or a file name)
DOTTED = re.compile(r"(?<![\w./$-])((?:jsgs|jsgstools)(?:\.[A-Za-z_]\w*)+)(?![\w/-]|\.\w)")
# a command: the program (or its module, `python -m jsgs.cli`, `torchrun ... -m jsgs.cli`), its subcommand,
# and the rest of that command (up to a pipe, a ; or &&; a | between alternatives, `[--method jsgs|gsplat]`,
# `[--resume | --force]`, is no pipe)
REST = r"((?:\[[^\]\n`]*\]|[^|;&\n`]|\|(?=[\w-]))*)"
COMMAND = re.compile(r"(?<![\w./-])(?:\S*/)?(jsgs|jsgstools)(?: |\.cli )([a-z][a-z-]*)(?![\w-])" + REST)
FENCE = re.compile(r"^```([^\n]*)\n(.*?)^```", re.MULTILINE | re.DOTALL)
SPAN = re.compile(r"`([^`\n]+(?:\n[^`\n]+)?)`")


def _code(text: str) -> list[str]:
    """The code of a Markdown page: its fenced blocks (continuation lines joined, shell comments dropped; a
    ``text`` block, such as a command's help, is prose) and its inline code spans."""
    code: list[str] = []
    prose = FENCE.sub("", text)
    for info, block in FENCE.findall(text):
        if info.strip() == "text":
            prose += "\n" + block
            continue
        # a continuation line (after a backslash, or a synopsis's indented `[--option ...]`) is its command's
        block = re.sub(r"\n[ \t]+(?=\[)", " ", block.replace("\\\n", " "))
        code.append("\n".join(re.sub(r"(^|\s)#\s.*", "", line) for line in block.splitlines()))
    return code + [s.replace("\n", " ") for s in SPAN.findall(prose)]


def _resolves(name: str) -> bool:
    import importlib

    parts = name.split(".")
    for i in range(len(parts), 0, -1):
        try:
            obj = importlib.import_module(".".join(parts[:i]))
        except ImportError:
            continue
        for attr in parts[i:]:
            if not hasattr(obj, attr):
                return False
            obj = getattr(obj, attr)
        return True
    return False


@pytest.mark.parametrize("page", DOCS, ids=lambda p: str(p.relative_to(ROOT)))
def test_dotted_names_in_docs_resolve(page: Path) -> None:
    """Every jsgs.x.y the page names (in its code) is a module, or an attribute of one."""
    names = {n for code in _code(page.read_text()) for n in DOTTED.findall(code)}
    bad = sorted(n for n in names if not _resolves(n))
    assert not bad, f"{page.relative_to(ROOT)}: names that do not resolve: {bad}"


def _commands() -> dict[str, dict[str, set[str]]]:
    """program -> subcommand -> the options it takes."""
    from jsgs.cli import main as jsgs_main
    from jsgstools.cli import main as tools_main

    out: dict[str, dict[str, set[str]]] = {}
    for prog, group in (("jsgs", jsgs_main), ("jsgstools", tools_main)):
        out[prog] = {
            name: {o for p in cmd.params for o in (*p.opts, *p.secondary_opts)} | {"--help", "-h"}
            for name, cmd in group.commands.items()
        }
    return out


@pytest.mark.parametrize("page", DOCS, ids=lambda p: str(p.relative_to(ROOT)))
def test_commands_in_docs_exist(page: Path) -> None:
    """Every `jsgs SUBCOMMAND ...` / `jsgstools SUBCOMMAND ...` in the page's code names a subcommand that
    exists, and every --option written after it is one that subcommand takes."""
    known = _commands()
    bad = []
    for code in _code(page.read_text()):
        for prog, sub, rest in COMMAND.findall(code):
            if sub not in known[prog]:
                bad.append(f"{prog} {sub}")
                continue
            for opt in re.findall(r"(?<![\w-])(--[a-z][a-z0-9-]*)", rest):
                if opt not in known[prog][sub]:
                    bad.append(f"{prog} {sub} {opt}")
    assert not bad, f"{page.relative_to(ROOT)}: commands that do not exist: {sorted(set(bad))}"


# what the docs write in place of a value: `--quality Q`, `--size WxH`, `--out RUN/x`, `--path FILE.json`
PLACEHOLDER = re.compile(r"[A-Z][A-Z0-9_]*(?:[./,][\w.]*)*|[A-Z]x[A-Z]|\.\.\.|…")


def _text_values() -> dict[tuple[str, str, str], Callable[[str], object]]:
    """The checks of the values of free-text options (a budget, a list of names or steps): each raises
    JsgsError on what the command refuses."""
    from jsgs.apps.camera_path import KINDS
    from jsgs.bench import plan
    from jsgs.train.config import cap_max_settings
    from jsgs.train.method import method_names

    def names(known: tuple[str, ...], pattern: str = "$^") -> Callable[[str], None]:
        def check(text: str) -> None:
            for name in plan.parse_list(text, "a list"):
                if name not in known and not re.fullmatch(pattern, name):
                    raise JsgsError(f"{name!r} is not one of {known}")

        return check

    def ints(text: str) -> list[int]:
        return plan.parse_list(text, "a list of integers", int)

    return {
        ("jsgs", "train", "--method"): names(tuple(method_names())),
        ("jsgs", "train", "--cap-max"): cap_max_settings, ("jsgs", "train", "--eval-at"): ints,
        ("jsgs", "bench", "--budgets"): plan.parse_budgets, ("jsgs", "bench", "--eval-at"): ints,
        ("jsgs", "bench", "--seeds"): ints, ("jsgs", "bench", "--fixed"): ints,
        ("jsgs", "bench", "--methods"): names(plan.METHODS),
        ("jsgs", "bench", "--schedules"): names(plan.SCHEDULES, plan._TWICE.pattern),
        ("jsgs", "render", "--path"): names(KINDS, r".+\.json"),
    }  # fmt: skip


def _refused_values(code: str) -> list[str]:
    """`PROG SUB --option VALUE` in ``code`` whose VALUE (each of `a|b|c`) the option refuses: not one of its
    choices, not of its type (an integer, a number), or refused by the command's own parsing of a free-text
    option (:func:`_text_values`); placeholders (:data:`PLACEHOLDER`, `$VAR`, `<x>`) are not values."""
    import click

    from jsgs.cli import main as jsgs_main
    from jsgstools.cli import main as tools_main

    groups, texts, bad = {"jsgs": jsgs_main, "jsgstools": tools_main}, _text_values(), []
    for prog, sub, rest in COMMAND.findall(code):
        command = groups[prog].commands.get(sub)
        for opt, value in re.findall(r"(?<![\w-])(--[a-z][a-z0-9-]*)(?:=| +)([^\s\[\]]+)", rest):
            param = next((p for p in getattr(command, "params", []) if opt in p.opts), None)
            if param is None or getattr(param, "is_flag", False) or param.nargs != 1:
                continue
            for v in (v.strip("'\"") for v in value.replace("\\|", "|").split("|")):
                if not v or v.startswith(("-", "$", "<", "~")) or PLACEHOLDER.fullmatch(v):
                    continue
                try:
                    param.type.convert(v, param, None)
                    texts.get((prog, sub, opt), str)(v)
                except (click.BadParameter, JsgsError) as e:
                    bad.append(f"{prog} {sub} {opt} {v}: {e}")
    return bad


@pytest.mark.parametrize("page", DOCS, ids=lambda p: str(p.relative_to(ROOT)))
def test_option_values_in_docs_are_accepted(page: Path) -> None:
    """Every value the page's code gives a `jsgs`/`jsgstools` option (`--schedule gaussian`, `--device
    auto|cuda|cpu`, `--cap-max auto`, `--budgets 300k,0.5x`) is one that option accepts."""
    bad = [b for code in _code(page.read_text()) for b in _refused_values(code)]
    assert not bad, f"{page.relative_to(ROOT)}: values the options refuse:\n" + "\n".join(bad)


def test_the_value_check_sees_refused_values() -> None:
    code = (
        "jsgs train m --jpeg-mode papr --device auto|gpu --seed 4x --cap-max lots --method jsgs\\|gsplt\n"
        "jsgs bench s --strategy mcmc --budgets 300k,half --schedules gaussian+r90,gausian --methods x\n"
        "jsgstools compress S --out D --schedule fixed --quality Q --subsampling 411 --jobs N\n"
        "jsgs render R --out v.mp4 --path spirl --path RUN/viewer_cameras.json\n"
    )
    found = [b.split(":")[0] for b in _refused_values(code)]
    assert found == [
        "jsgs train --jpeg-mode papr", "jsgs train --device gpu", "jsgs train --seed 4x",
        "jsgs train --cap-max lots", "jsgs train --method gsplt", "jsgs bench --budgets 300k,half",
        "jsgs bench --schedules gaussian+r90,gausian", "jsgs bench --methods x",
        "jsgstools compress --subsampling 411", "jsgs render --path spirl",
    ]  # fmt: skip
    synopsis = "```\njsgs train MANIFEST --out RUN\n           [--device gpu] [--seed 42]\n```\n"
    found = [b.split(":")[0] for c in _code(synopsis) for b in _refused_values(c)]
    assert found == ["jsgs train --device gpu"], "a synopsis's indented [--option] line is its command's"


def _shown_default_is_the_code(param: object, value: str) -> bool:
    """Whether ``value``, which a synopsis shows for an option (`[--seed 0]`), is the option's default: its
    click default, or a value its help's ``[default: ...]`` names."""
    default = getattr(param, "default", None)
    if default is not None and (str(default) == value or _same(_doc_value(value), default)):
        return True
    said = re.findall(r"\[default: ([^\]]*)\]", re.sub(r"\s+", " ", getattr(param, "help", None) or ""))
    alone = rf"(?<![\w.])(?<!\w,){re.escape(value)}(?![\w.]|,\w)"  # 8 in "8, or ...", not in "30,80"
    return bool(said) and re.search(alone, said[0]) is not None


@pytest.mark.parametrize("page", DOCS, ids=lambda p: str(p.relative_to(ROOT)))
def test_defaults_shown_in_synopses_are_the_code(page: Path) -> None:
    """An option a page's synopsis shows with a value in brackets (`[--test-every 8]`, not a placeholder
    such as `[--quality Q]`) shows its default."""
    from jsgs.cli import main as jsgs_main
    from jsgstools.cli import main as tools_main

    groups = {"jsgs": jsgs_main, "jsgstools": tools_main}
    bad = []
    for code in _code(page.read_text()):
        for prog, sub, rest in COMMAND.findall(code):
            command = groups[prog].commands.get(sub)
            for opt, value in re.findall(r"\[(--[a-z][a-z0-9-]*) ([^\]\s|]+)\]", rest):
                params = [p for p in getattr(command, "params", []) if opt in p.opts]
                if params and not re.fullmatch(r"[A-Z][A-Z_]*|[A-Z]x[A-Z]|WxH", value):
                    if not _shown_default_is_the_code(params[0], value):
                        bad.append(f"{prog} {sub} [{opt} {value}]")
    assert not bad, f"{page.relative_to(ROOT)}: values shown that are not the defaults: {bad}"


def test_the_checks_see_bad_names_and_commands() -> None:
    page = (
        "Call `jsgs.train.train(m, out)` or `jsgs.train.trainer.train`.\n\n"
        "```bash\njsgs train m.json --out r --methd jsgs  # jsgs fly --no\n"
        ".venv/bin/jsgstools sfmm photos\ntorchrun --nproc-per-node 2 -m jsgs.cli train m --gpu 2 | tee log\n"
        "jsgs bench [--strategy default|mcmc] [--resume | --forc] [--budget 3]\n```\n"
    )
    names = {n for code in _code(page) for n in DOTTED.findall(code)}
    assert names == {"jsgs.train.train", "jsgs.train.trainer.train", "jsgs.cli"}
    assert [_resolves(n) for n in sorted(names)] == [True, False, True]
    cmds = [(p, s, re.findall(r"--[a-z-]+", r)) for code in _code(page) for p, s, r in COMMAND.findall(code)]
    assert cmds == [
        ("jsgs", "train", ["--out", "--methd"]), ("jsgstools", "sfmm", []), ("jsgs", "train", ["--gpu"]),
        ("jsgs", "bench", ["--strategy", "--resume", "--forc", "--budget"]),
    ]  # fmt: skip
    known = _commands()
    assert "--methd" not in known["jsgs"]["train"] and "sfmm" not in known["jsgstools"]
    assert "--gpu" not in known["jsgs"]["train"] and "--budget" not in known["jsgs"]["bench"]


# a script of the repository's own (tools/…, benchmarks/…, scripts/…, or its file name alone where that is one
# script's) and the rest of the command that runs it
SCRIPT = re.compile(r"(?<![\w.-])((?:[\w.-]+/)*[A-Za-z_]\w*\.py)(?![\w.])" + REST)
SCRIPTS = sorted(p for folder in ("tools", "benchmarks", "scripts") for p in (ROOT / folder).rglob("*.py"))


def _script_options(code: str) -> list[tuple[Path, list[str]]]:
    """(script, the --options written after it) of each run of a repository script in ``code``; a shell
    variable set to a script (``P=tools/x.py`` … ``$P --steps 5``) is that script."""
    assignment = r"(?m)^\s*(\w+)=(\S+\.py)\s*$"
    for name, value in re.findall(assignment, code):
        code = re.sub(rf"\${{?{name}\b}}?", value, code)
    out = []
    for path, rest in SCRIPT.findall(re.sub(assignment, "", code)):
        named = Path(path).name
        found = [ROOT / path] if (ROOT / path).is_file() else [p for p in SCRIPTS if p.name == named]
        if len(found) == 1 and found[0] in SCRIPTS:
            out.append((found[0], re.findall(r"(?<![\w-])(--[a-z][a-z0-9-]*)", rest)))
    return out


def _takes(source: str, option: str) -> bool:
    """Whether a script's source declares ``option`` (argparse: the option's string; ``--no-x`` of a
    BooleanOptionalAction ``--x``)."""
    if f'"{option}"' in source or f"'{option}'" in source:
        return True
    return option.startswith("--no-") and f'"--{option[5:]}"' in source and "BooleanOptionalAction" in source


@pytest.mark.parametrize("page", DOCS, ids=lambda p: str(p.relative_to(ROOT)))
def test_script_options_in_docs_exist(page: Path) -> None:
    """Every --option the page's code passes to a script of tools/, benchmarks/ or scripts/ is one that
    script declares."""
    bad = sorted(
        f"{script.relative_to(ROOT)} {opt}"
        for code in _code(page.read_text())
        for script, opts in _script_options(code)
        for opt in opts if not _takes(script.read_text(), opt)
    )  # fmt: skip
    assert not bad, f"{page.relative_to(ROOT)}: options the scripts do not take: {bad}"


def test_options_named_alone_exist() -> None:
    """An option the docs name on its own (`--cap-max N`, `--pairs`) is one that a jsgs or jsgstools
    command or a repository script takes."""
    known = set().union(*(opts for prog in _commands().values() for opts in prog.values()))
    sources = [p.read_text() for p in SCRIPTS]
    bad = sorted(
        f"{page.relative_to(ROOT)}: {opt}"
        for page in DOCS
        for code in _code(page.read_text()) if code.lstrip().startswith("--")
        for opt in re.findall(r"(?<![\w-])(--[a-z][a-z0-9-]*)", code)
        if opt not in known and not any(_takes(s, opt) for s in sources)
    )  # fmt: skip
    assert not bad, "options no command or script takes:\n" + "\n".join(bad)


# `make TARGET`, and a shell script run with settings in its environment (`PART=toy bash tools/x.sh`, also
# through scripts/gpu_run.sh, which runs its command with the environment it is given)
MAKE = re.compile(r"(?<![\w-])make ([a-z][\w-]*)")
SHELL_RUN = re.compile(
    r"((?:[A-Z][A-Z0-9_]*=\S+ )+)(?:bash )?(?:scripts/gpu_run\.sh (?:bash )?)?"
    r"(?!scripts/gpu_run\.sh)((?:tools|scripts|benchmarks)/[\w/.-]+\.sh)"
)


def _bad_make_and_shell_runs(code: str) -> list[str]:
    """The `make` targets the Makefile lacks and the VAR=value settings a shell script does not read (its
    source does not name the variable, or the value where that is a named choice)."""
    targets = set(re.findall(r"(?m)^([\w-]+):", (ROOT / "Makefile").read_text()))
    bad = [f"make {t}" for t in MAKE.findall(code) if t not in targets]
    for settings, script in SHELL_RUN.findall(code):
        path = ROOT / script
        source = path.read_text() if path.is_file() else ""
        for var, value in re.findall(r"([A-Z][A-Z0-9_]*)=(\S+)", settings):
            choice = re.fullmatch(r"[a-z][a-z0-9_]*", value)  # a named choice (PART=toy), not a number
            if not re.search(rf"\b{var}\b", source) or (choice and not re.search(rf"\b{value}\b", source)):
                bad.append(f"{var}={value} {script}")
    return bad


def test_make_targets_and_script_settings_in_docs_exist() -> None:
    """Every `make TARGET` the docs write is a Makefile target, and every VAR=value a page sets for a
    repository shell script (`PART=toy tools/campaigns/gc_every.sh`) is a variable and value it reads."""
    bad = [f"{page.relative_to(ROOT)}: {b}" for page in DOCS for code in _code(page.read_text())
           for b in _bad_make_and_shell_runs(code)]  # fmt: skip
    assert not bad, "\n".join(bad)
    assert _bad_make_and_shell_runs("make demoo; PART=toyy tools/campaigns/gc_every.sh; make test") == [
        "make demoo", "PART=toyy tools/campaigns/gc_every.sh"]  # fmt: skip
    assert not _bad_make_and_shell_runs("PART=toy bash tools/campaigns/gc_every.sh")
    assert _bad_make_and_shell_runs("PART=toyy bash scripts/gpu_run.sh bash tools/campaigns/gc_every.sh") == [
        "PART=toyy tools/campaigns/gc_every.sh"]  # fmt: skip


def test_the_script_check_sees_bad_options() -> None:
    code = (
        "P=tools/diagnostics/profile_step.py\n$P --pairs 5 --pears 2\n"
        "python benchmarks/bench_jpeg_ops.py --fused-jo | tee x --nothing\n"
        "profile_step.py --no-fresh; tests/test_docs.py --x\n"
    )
    found = [(s.name, o) for s, o in _script_options(code)]
    assert found == [
        ("profile_step.py", ["--pairs", "--pears"]), ("bench_jpeg_ops.py", ["--fused-jo"]),
        ("profile_step.py", ["--no-fresh"]),
    ]  # fmt: skip
    source = (ROOT / "tools" / "diagnostics" / "profile_step.py").read_text()
    assert _takes(source, "--pairs") and _takes(source, "--no-fresh") and not _takes(source, "--pears")


# a path into the repository's own folders (jsgs/…, tests/…, tools/…), not part of a longer path or a URL
REPO_PATH = re.compile(r"(?<![\w./-])((?:jsgs|jsgstools|tests|tools|scripts|benchmarks)/[\w./*-]*[\w*])")
# what the shipped code and the docs write about the code: its sources, scripts and every page but the
# recorded profiler frames (docs/results/budget/speed/gaps_*.md name the files of the code they measured)
SHIPPED = sorted(
    p for folder in ("jsgs", "jsgstools", "scripts", "tools", "benchmarks")
    for p in (ROOT / folder).rglob("*") if p.suffix in {".py", ".sh", ".md"} and p.is_file()
)  # fmt: skip
WRITTEN = [p for p in (*DOCS, *SHIPPED) if not re.search(r"docs/results/budget/speed/gaps_", str(p))]


def _missing_paths(text: str) -> list[str]:
    """The repository paths ``text`` names (globs allowed) that match nothing in the checkout."""
    paths = {m.rstrip(".") for m in REPO_PATH.findall(text)}
    return sorted(p for p in paths if not any(ROOT.glob(p)) and not any(ROOT.glob(p + "*")))


def test_paths_in_docs_and_code_exist() -> None:
    """Every jsgs/…, jsgstools/…, tests/…, tools/…, scripts/… and benchmarks/… path that the docs or the
    shipped code's comments and docstrings write down exists (a file moved leaves no stale path)."""
    bad = [f"{p.relative_to(ROOT)}: {m}" for p in WRITTEN for m in _missing_paths(p.read_text())]
    assert not bad, "\n".join(bad)


# the file types a code's string may name (``"jsgs.json"``): not dotted names of the code
FILE_TYPES = {"json", "py", "md", "csv", "txt", "png", "ply", "pt", "log", "toml", "sh", "tgz"}


def test_dotted_names_in_code_resolve() -> None:
    """Every jsgs.x.y that the shipped code's comments, docstrings and scripts name is a module, or an
    attribute of one (a renamed or moved definition leaves no stale name)."""
    bad = sorted(
        f"{p.relative_to(ROOT)}: {n}"
        for p in SHIPPED if p.suffix != ".md"
        for n in set(DOTTED.findall(p.read_text()))
        if n.rpartition(".")[2] not in FILE_TYPES and not _resolves(n)
    )  # fmt: skip
    assert not bad, "\n".join(bad)


def test_the_path_check_sees_stale_paths() -> None:
    text = "See jsgs/ssim.py, tests/jsgs/ and `jsgs/kernels/_torch_impl.py`; runs in tools/campaigns/*.sh."
    assert _missing_paths(text) == ["jsgs/ssim.py", "tests/jsgs"]


def test_the_demo_writes_its_block_of_the_readme() -> None:
    """README.md has one fenced demo-output block, and scripts/demo_readme.py (which scripts/demo.sh runs)
    replaces exactly that block with what the demo printed, long lines shortened."""
    sys.path.insert(0, str(ROOT / "scripts"))
    try:
        import demo_readme
    finally:
        sys.path.pop(0)
    readme = (ROOT / "README.md").read_text()
    block = re.escape(demo_readme.BEGIN) + r"\n```\n(.*?)\n```\n" + re.escape(demo_readme.END)
    assert len(re.findall(block, readme, re.DOTALL)) == 1, "README.md: one demo-output block, fenced"
    assert "demo_readme.py" in (ROOT / "scripts" / "demo.sh").read_text()
    new = demo_readme.replace(readme, "== 1. x\n" + "y" * 200 + "\n")
    assert re.findall(block, new, re.DOTALL) == ["== 1. x\n" + "y" * 109 + "…"]
    assert new.split(demo_readme.BEGIN)[0] == readme.split(demo_readme.BEGIN)[0]
    assert new.split(demo_readme.END)[1] == readme.split(demo_readme.END)[1]


def test_the_readme_demo_block_has_the_demos_shape() -> None:
    """The README's demo block has every line the demo prints (scripts/demo_readme.py SHAPE, in order), its
    metrics table agrees with the runs' own summary lines and with the comparison line, and the demo
    refuses output that lacks a line (a run without LPIPS, one that stopped early)."""
    sys.path.insert(0, str(ROOT / "scripts"))
    try:
        import demo_readme
    finally:
        sys.path.pop(0)
    readme = (ROOT / "README.md").read_text()
    text = re.findall(re.escape(demo_readme.BEGIN) + r"\n```\n(.*?)\n```\n", readme, re.DOTALL)[0]
    gap = demo_readme.missing(text)
    assert gap is None, f"README.md demo block: no line like {gap!r}"
    done = r"^(gsplat|jsgs): complete: .*PSNR ([\d.]+), SSIM ([\d.]+), LPIPS ([\d.]+)"
    summary = {m: (p, s, lp) for m, p, s, lp in re.findall(done, text, re.M)}
    row = r"^(gsplat|jsgs) +([\d.]+) +([\d.]+) +([\d.]+) "
    table = {m: (p, s, lp) for m, p, s, lp in re.findall(row, text, re.M)}
    assert summary == table and set(table) == {"gsplat", "jsgs"}
    (gp, _, gl), (jp, _, jl) = ((float(x) for x in table[m]) for m in ("gsplat", "jsgs"))
    line = re.search(r"^JSGS against gsplat: LPIPS (\S+) %, PSNR (\S+) dB", text, re.M)
    assert line is not None
    assert abs(float(line[1]) - 100 * (jl / gl - 1)) < 0.2 and abs(float(line[2]) - (jp - gp)) < 0.002
    met = "met" if jl <= 0.95 * gl and jp >= gp else "NOT met"
    assert f"PSNR not lower): {met}" in text
    for drop in ("== 8. a test view side by side", "jsgs: complete:"):
        broken = "\n".join(x for x in text.splitlines() if not x.startswith(drop))
        assert demo_readme.missing(broken) is not None


def test_every_schema_is_listed() -> None:
    """docs/formats.md lists every schema the package ships, so each file jsgs writes is described there."""
    text = (ROOT / "docs" / "formats.md").read_text()
    shipped = sorted(p.name for p in (ROOT / "jsgs" / "schemas").glob("*.schema.json"))
    missing = [name for name in shipped if f"`jsgs/schemas/{name}`" not in text]
    assert not missing, f"docs/formats.md does not list {missing}"


# ---------------------------------------------------------------------------------------------------------
# the defaults the docs state are the code's


def _flat(obj: object, prefix: str = "") -> dict[str, object]:
    """A settings dataclass's values by dotted name (``speed.fused_jo``), sections expanded."""
    import dataclasses

    out: dict[str, object] = {}
    for f in dataclasses.fields(obj):  # type: ignore[arg-type]
        value = getattr(obj, f.name)
        if dataclasses.is_dataclass(value):
            out.update(_flat(value, f"{prefix}{f.name}."))
        else:
            out[prefix + f.name] = value
    return out


def _doc_value(text: str) -> object:
    """A value as a page writes it (``true``, ``1e-3``, ``1.0 px``, ``300,000``, `` `paper` ``)."""
    text = text.strip().strip("`").strip()
    if text in ("true", "false"):
        return text == "true"
    number = re.fullmatch(r"(-?[\d,]*\.?\d+(?:e-?\d+)?)(?: ?[a-z]+)?", text)
    if number:
        return float(number[1].replace(",", ""))
    return text


def _same(doc: object, code: object) -> bool:
    if isinstance(doc, float):
        return isinstance(code, int | float) and not isinstance(code, bool) and doc == float(code)
    return doc == code


def _option_rows(text: str) -> list[tuple[str, object]]:
    """(name, documented default) of every row of the page's ``| key | default | ... |`` tables: a row names
    one or more keys (`` `a`, `b` ``, a command-line switch in brackets after them) and as many defaults,
    or one default for all of them."""
    rows: list[tuple[str, object]] = []
    for table in re.findall(r"^\| key \| default \|.*\n\|[-| ]+\|\n((?:\|.*\n?)+)", text, re.M):
        for line in table.splitlines():
            key, default = (c.strip() for c in line.strip("|").split("|")[:2])
            names = [n for n in re.findall(r"`([^`]+)`", key.split("(")[0]) if not n.startswith("-")]
            values = default.split(", ")
            assert names and len(values) in (1, len(names)), f"cannot read the row {line[:80]!r}"
            if len(values) == 1:
                values *= len(names)
            rows += [(n, _doc_value(v)) for n, v in zip(names, values, strict=True)]
    return rows


def test_method_options_table_is_the_code() -> None:
    """docs/method.md's table of ``method_options`` lists every option of ``--method jsgs`` (its speed
    section included) with the default of jsgs.method.options.JsgsOptions."""
    from jsgs.method.options import JsgsOptions

    code = _flat(JsgsOptions())
    rows = _option_rows((ROOT / "docs" / "method.md").read_text())
    documented = dict(rows)
    assert len(documented) == len(rows), "docs/method.md: an option listed twice"
    unknown = sorted(set(documented) - set(code))
    missing = sorted(set(code) - set(documented))
    wrong = [f"{n}: {documented[n]!r}, code {code[n]!r}" for n in documented
             if n in code and not _same(documented[n], code[n])]  # fmt: skip
    assert not (unknown or missing or wrong), (
        f"docs/method.md method_options table: not options {unknown}; not listed {missing}; "
        f"defaults that differ {wrong}"
    )


def test_the_table_check_reads_rows() -> None:
    page = (
        "| key | default | |\n|---|---|---|\n"
        "| `a`, `b` (`--a`) | 0.2, 1e-3 | x |\n| `c`, `d` (`--no-c`) | true | |\n"
        "| `speed.e` (`--e`) | `auto` | |\n| `f` | 1.0 px | |\n\nafter\n"
    )
    assert _option_rows(page) == [("a", 0.2), ("b", 1e-3), ("c", True), ("d", True), ("speed.e", "auto"),
                                  ("f", 1.0)]  # fmt: skip
    assert _same(1.0, 1) and not _same(1.0, True) and not _same("auto", True) and _same(False, False)


def _row(text: str, first: str) -> str:
    """The table row of ``text`` whose first cell starts with ``first``."""
    rows = [r for r in text.splitlines() if r.startswith(f"| {first}")]
    assert len(rows) == 1, f"no single table row starting {first!r}"
    return rows[0]


def _numbers(pattern: str, text: str) -> list[float]:
    """The numbers of ``pattern``'s groups in ``text`` (``300,000`` -> 300000.0); the pattern must match."""
    m = re.search(pattern, text)
    assert m, f"docs/training.md no longer says {pattern!r}: update the check with the page"
    return [float(g.replace(",", "")) for g in m.groups()]


def test_training_presets_are_the_code() -> None:
    """docs/training.md's presets table and its table of the paper's values state the settings that
    jsgs.train.config's presets and JSGS's recipes (jsgs.method.recipes.RECIPES) give."""
    from jsgs.method.recipes import RECIPES
    from jsgs.train.config import TrainConfig

    text = (ROOT / "docs" / "training.md").read_text()
    mcmc, paper = TrainConfig.from_preset("mcmc"), TrainConfig.from_preset("paper")
    row = _row(text, "`mcmc` (default)")
    assert _numbers(r"([\d,]+) steps \(`max_steps`\)", row) == [mcmc.iterations]
    assert _numbers(r"evaluations at ([\d,]+) and ([\d,]+)", row) == mcmc.eval_at
    s = mcmc.strategy
    assert s.type == "mcmc" and "MCMCStrategy" in row
    assert _numbers(r"refining from ([\d,]+) to ([\d,]+) every ([\d,]+) steps", row) == [
        s.refine_start_iter, s.refine_stop_iter, s.refine_every]  # fmt: skip
    assert s.cap_max_auto and "budget sized to the scene (`strategy.cap_max_auto`" in row
    assert _numbers(r"`strategy.cap_max` = ([\d,]+) Gaussians when `cap_max_auto` is off", row) == [s.cap_max]
    assert _numbers(r"init opacity ([\d.]+) and scale ([\d.]+)", row) == [mcmc.init.opacity, mcmc.init.scale]
    assert _numbers(r"opacity and scale regularisation ([\d.]+)", row) * 2 == [
        mcmc.loss.opacity_reg, mcmc.loss.scale_reg]  # fmt: skip
    recipe = re.search(r"for JSGS the method options (.*?) \(`jsgs.method.recipes.RECIPES`", row)
    assert recipe
    given = {k: _doc_value(v) for k, v in re.findall(r"`(\w+)` ([\w.]+)", recipe[1])}
    jsgs_mcmc = RECIPES["mcmc"]
    recipe_ok = set(given) == set(jsgs_mcmc) and all(_same(given[k], v) for k, v in jsgs_mcmc.items())
    assert recipe_ok, (given, jsgs_mcmc)
    assert "paper" not in RECIPES, "docs/training.md: the paper preset gives JSGS the paper's weights"

    row = _row(text, "`paper`")
    assert _numbers(r"([\d,]+) steps with evaluations at ([\d,]+), ([\d,]+) and ([\d,]+)", row) == [
        paper.iterations, *paper.eval_at]  # fmt: skip
    assert paper.strategy.type == "default" and "DefaultStrategy" in row
    dens = _row(text, "densification")
    named = {k: _doc_value(v) for k, v in re.findall(r"(\w+) (\d[\d.e-]*)(?=,| \|)", dens)}
    assert {k: v for k, v in named.items() if k not in ("refine", "every")} == {
        k: getattr(paper.strategy, k) for k in ("grow_grad2d", "grow_scale3d", "prune_opa", "prune_scale3d",
                                                "reset_every")}, named  # fmt: skip
    ps = paper.strategy
    assert _numbers(r"refine ([\d,]+)…([\d,]+) every ([\d,]+)", dens) == [
        ps.refine_start_iter, ps.refine_stop_iter, ps.refine_every]  # fmt: skip
    o = paper.optim
    opt = _row(text, "optimiser")
    assert _numbers(r"Adam \(eps ([\de.-]+)\)", opt) == [o.eps]
    assert _numbers(r"means ([\de.-]+) × scene scale decaying exponentially to ([\d.]+)×", opt) == [
        o.means_lr, o.means_lr_final_factor]  # fmt: skip
    lr = r"([\de.-]+)"
    lrs = _numbers(rf"scales {lr}, quats {lr}, opacities {lr}, sh0 {lr}, shN {lr}/(\d+)", opt)
    assert lrs[:4] == [o.scales_lr, o.quats_lr, o.opacities_lr, o.sh0_lr] and lrs[4] / lrs[5] == o.shN_lr
    assert _numbers(r"opacity ([\d.]+);", _row(text, "init")) == [paper.init.opacity]
    assert _numbers(r"one more every (\d+) steps", _row(text, "SH")) == [paper.render.sh_degree_interval]
    assert _numbers(r"seed (\d+)", _row(text, "views")) == [paper.seed]


# how a page states a setting's default in its prose: `speed.fused_jo`, `auto` by default; `tables: effective`
# (default `header`); `optim.means_lr_decay_steps` (0, the default ...); `checkpoint_keep` (default 3 ...)
DEFAULT_CLAIMS = (
    r"`(?:method_options\.)?([\w.]+)`,? `([^`]+)` by default",
    r"`(?:method_options\.)?([\w.]+): [^`]+` \(default `?([^`),]+)`?\)",
    r"`(?:method_options\.)?([\w.]+)` \(([^,()]+), the default",
    r"`(?:method_options\.)?([\w.]+)` \(default:? `?([^`\s,;)]+)`?",
)


def _default_claims(text: str) -> list[tuple[str, object]]:
    text = re.sub(r"\s+", " ", text)
    return [(n, _doc_value(v)) for p in DEFAULT_CLAIMS for n, v in re.findall(p, text)]


def test_defaults_stated_in_prose_are_the_code() -> None:
    """Where a page says in a sentence what a setting's default is, it is the code's: a training setting's
    (jsgs.train.config.TrainConfig, the default preset) or a JSGS option's (JsgsOptions)."""
    from jsgs.method.options import JsgsOptions
    from jsgs.train.config import TrainConfig

    train, jsgs = _flat(TrainConfig()), _flat(JsgsOptions())
    claims, bad = 0, []
    for page in DOCS:
        for name, value in _default_claims(page.read_text()):
            claims += 1
            code = [c[name] for c in (train, jsgs) if name in c]
            if len(code) != 1 or not _same(value, code[0]):
                bad.append(f"{page.relative_to(ROOT)}: {name} {value!r}, code {code or 'no such setting'}")
    assert not bad, "\n".join(bad)
    assert claims >= 4, "the docs' default claims are no longer found: update DEFAULT_CLAIMS with the pages"


def test_the_prose_check_reads_claims() -> None:
    text = (
        "A (`method_options.speed.fused_jo`, `auto` by default: on) and `method_options.tables: effective`\n"
        "(default `header`); `optim.means_lr_decay_steps` (0, the default: the end) and `checkpoint_keep`\n"
        "(default 3, the newest)."
    )
    assert _default_claims(text) == [
        ("speed.fused_jo", "auto"), ("tables", "header"), ("optim.means_lr_decay_steps", 0.0),
        ("checkpoint_keep", 3.0),
    ]  # fmt: skip


def test_defaults_in_the_train_help_are_the_code() -> None:
    """The defaults `jsgs train --help` writes into its options' help (which start as None, so that a preset
    or a config file decides) are the settings' and the method options' defaults, and each preset's
    length and evaluation steps."""
    from jsgs.cli import main
    from jsgs.method.flags import FLAGS
    from jsgs.method.options import JsgsOptions
    from jsgs.train.config import DEFAULT_PRESET, TrainConfig

    train, jsgs = _flat(TrainConfig()), _flat(JsgsOptions())
    flags = {f.flag: f.option for f in FLAGS}
    checked, bad = set(), []
    for p in main.commands["train"].params:
        help_text = re.sub(r"\s+", " ", getattr(p, "help", None) or "")
        if p.name in ("iterations", "eval_at"):
            per_preset = re.findall(r"(\d[\d,]*) for (\w+)", help_text)
            assert {name for _, name in per_preset} >= {"mcmc", "paper"}, (p.name, help_text)
            for value, name in per_preset:
                code = getattr(TrainConfig.from_preset(name), p.name)
                if [int(v) for v in value.split(",")] != (code if isinstance(code, list) else [code]):
                    bad.append(f"{p.opts[0]} for {name}: {value}, code {code}")
            checked.add(p.name)
            continue
        m = re.search(r"\[default: ([^\]\s]+)\]", help_text)
        if not m:
            continue
        opt = p.opts[0]
        if opt in flags:
            code = jsgs[flags[opt]]
        elif p.name == "preset":
            code = DEFAULT_PRESET
        elif p.name == "cap_max":  # auto (strategy.cap_max_auto) or the fixed strategy.cap_max
            code = "auto" if train["strategy.cap_max_auto"] else train["strategy.cap_max"]
        else:
            keys = [k for k in (p.name, f"strategy.{p.name}") if k in train]
            assert keys, f"{opt}: [default: {m[1]}] of no setting"
            code = train[keys[0]]
        if not _same(_doc_value(m[1]), code):
            bad.append(f"{opt}: [default: {m[1]}], code {code!r}")
        checked.add(p.name)
    assert not bad, "\n".join(bad)
    assert {"iterations", "eval_at", "seed", "method", "preset", "jpeg_mode"} <= checked, checked


def _preset_help_differs(help_text: str) -> list[str]:
    """What `jsgs train --preset`'s help says of the presets that their settings do not give: the mcmc
    preset's length, evaluations, refinement and every `section.key value` it names; the paper and preview
    presets' lengths."""
    from jsgs.train.config import TrainConfig

    text = re.sub(r"\s+", " ", help_text)
    mcmc, bad = TrainConfig.from_preset("mcmc"), []
    said = re.search(r"mcmc \(the defaults\): (.*?); paper: (.*?); preview: (.*)", text)
    mcmc_steps = r"\((\d+) steps, evaluations at (\d+) and (\d+), MCMCStrategy refining until step (\d+)"
    steps = re.search(mcmc_steps, said[1] if said else "")
    assert said and steps, f"jsgs train --preset's help no longer reads as this check expects: {text[:200]!r}"
    if [int(n) for n in steps.groups()] != [mcmc.iterations, *mcmc.eval_at, mcmc.strategy.refine_stop_iter]:
        bad.append(f"mcmc: {steps[0]}")
    flat = _flat(mcmc)
    for key, value in re.findall(r"\b((?:init|optim|strategy|loss|render)\.\w+)(?: =)? ([\d.]+)", said[1]):
        if key not in flat or not _same(float(value), flat[key]):
            bad.append(f"mcmc: {key} {value}, code {flat.get(key, 'no such setting')}")
    for name, part in (("paper", said[2]), ("preview", said[3])):
        code, given = TrainConfig.from_preset(name).iterations, re.findall(r"(\d+) steps", part)
        if given != [str(code)]:
            bad.append(f"{name}: {', '.join(given)} steps, code {code}")
    return bad


def test_the_preset_help_is_the_code() -> None:
    """`jsgs train --preset`'s help states each preset's settings as jsgs.train.config's presets give them
    (the JSGS recipe part is generated from them)."""
    from jsgs.cli import main

    text = next(p for p in main.commands["train"].params if p.name == "preset").help or ""
    assert _preset_help_differs(text) == []
    changed = text.replace("init.opacity 0.5", "init.opacity 0.3").replace("1000 steps", "900 steps")
    expected = ["mcmc: init.opacity 0.3, code 0.5", "preview: 900 steps, code 1000"]
    assert _preset_help_differs(changed) == expected


def test_the_synopsis_check_sees_other_values() -> None:
    from jsgs.cli import main as jsgs_main
    from jsgstools.cli import main as tools_main

    def param(group: object, sub: str, opt: str) -> object:
        return next(p for p in group.commands[sub].params if opt in p.opts)  # type: ignore[attr-defined]

    t, j = tools_main, jsgs_main
    shown = [
        (t, "compress", "--test-every", "8", True), (t, "compress", "--test-every", "9", False),
        (t, "manifest", "--test-every", "8", True), (j, "train", "--seed", "42", True),
        (j, "train", "--eval-at", "7000,30000", True), (j, "train", "--eval-at", "7000", False),
        (j, "render", "--fps", "30", True), (j, "render", "--fps", "24", False),
    ]  # fmt: skip
    for group, sub, opt, value, ok in shown:
        assert _shown_default_is_the_code(param(group, sub, opt), value) is ok, (sub, opt, value)


# a setting's dotted name as the docs write it: `strategy.cap_max`, `method_options.speed.fused_jo`
SETTING = re.compile(
    r"(?<![\w./-])(method_options\.[a-z_]+(?:\.[a-z_]+)?|(?:init|optim|strategy|scene|render|loss|speed|eval)"
    r"\.[a-z_]+)(?![\w(/-]|\.\w)"
)


def _unknown_settings(code: str) -> list[str]:
    from jsgs.method.options import JsgsOptions
    from jsgs.train.config import TrainConfig

    train, jsgs = _flat(TrainConfig()), _flat(JsgsOptions())
    out = []
    for name in SETTING.findall(code):
        if name.startswith("method_options."):
            known = name.removeprefix("method_options.") in (*jsgs, "speed")
        else:
            known = name in train or name in jsgs  # speed.fused_jo: the JSGS options' speed section
        if not known:
            out.append(name)
    return out


@pytest.mark.parametrize("page", DOCS, ids=lambda p: str(p.relative_to(ROOT)))
def test_settings_named_in_docs_exist(page: Path) -> None:
    """Every setting the page's code names by its dotted path (`strategy.cap_max`, `loss.base_weight`,
    `method_options.base_noise`, `speed.fused_jo`) is a training setting or a JSGS option."""
    bad = sorted({n for code in _code(page.read_text()) for n in _unknown_settings(code)})
    assert not bad, f"{page.relative_to(ROOT)}: settings that do not exist: {bad}"


def test_the_settings_check_sees_unknown_names() -> None:
    code = "`strategy.cap_max`, `loss.base_wieght`, `method_options.speed.fused_jo`, `method_options.tabels`"
    assert _unknown_settings(code + " jsgs/train/config.py, `speed.ssim_kernel`") == [
        "loss.base_wieght", "method_options.tabels"]  # fmt: skip



@functools.cache
def _derived_names() -> frozenset[str]:
    """What a run's config.json may record in ``derived`` (its schema's names)."""
    from jsgs.train.config import config_schema

    return frozenset(config_schema()["properties"]["derived"]["properties"])


def _unknown_derived(code: str) -> list[str]:
    """The `derived.x` values of a run's config.json that ``code`` names and its schema does not have."""
    return [n for n in re.findall(r"(?<![\w.])derived\.([a-z_]+)", code) if n not in _derived_names()]


def test_derived_values_named_in_docs_exist() -> None:
    """Every `derived.x` the docs name (what a run's config.json records it derived: `derived.budget`,
    `derived.method`) is one that config.json's schema has."""
    bad = sorted({f"{page.relative_to(ROOT)}: derived.{n}" for page in DOCS
                  for code in _code(page.read_text()) for n in _unknown_derived(code)})  # fmt: skip
    assert not bad, "\n".join(bad)
    assert _unknown_derived("`derived.budget`, `derived.budgets`, `settings.derived.x`") == ["budgets"]

# ---------------------------------------------------------------------------------------------------------
# docs/results/README.md's index: every results folder reached, and each row's status its folder's own

RESULTS = ROOT / "docs" / "results"
STATUS_WORDS = ("current", "partial", "superseded", "rejected", "not re-measured")


def _status_words(text: str) -> set[str]:
    """The status words of a status text (``current, partial (CPU only)``), parenthesised asides left out."""
    text = re.sub(r"\([^)]*\)", "", text.replace("*", ""))
    return {w for w in STATUS_WORDS if re.search(rf"\b{w}\b", text, re.IGNORECASE)}


def _folder_status(readme: Path) -> set[str]:
    """The status a results folder's README opens with (``**Status: current, partial** — ...``)."""
    m = re.search(r"Status:\**\s*(.*?)(?:—|\. |\n)", readme.read_text())
    assert m, f"{readme.relative_to(ROOT)}: no 'Status:' line"
    return _status_words(m[1])


def test_results_index_is_the_folders() -> None:
    """Every results folder with a README is linked from docs/results/README.md or from its parent folder's
    README, every page directly in docs/results from the index, and each index row's status (current,
    partial, superseded, rejected, not re-measured) is the one its folder's README states."""
    index = (RESULTS / "README.md").read_text()
    unlinked = []
    for readme in sorted(RESULTS.rglob("README.md")):
        folder = readme.parent
        if folder == RESULTS or "paper_protocol/runs" in str(folder):
            continue
        rel = folder.relative_to(RESULTS).as_posix()
        parent = folder.parent / "README.md"
        in_parent = parent.is_file() and f"]({folder.name}/" in parent.read_text()
        if f"]({rel}/" not in index and not in_parent:
            unlinked.append(f"{rel}/")
    for page in sorted(RESULTS.glob("*.md")):
        if page.name != "README.md" and f"]({page.name})" not in index:
            unlinked.append(page.name)
    assert not unlinked, f"docs/results/README.md does not reach {unlinked}"
    differ = []
    for row in re.findall(r"^\| \[.*$", index, re.M):
        cells = [c.strip() for c in row.strip("|").split("|")]
        for target in re.findall(r"\]\(([\w/.-]+/README\.md)\)", cells[0]):
            own, said = _folder_status(RESULTS / target), _status_words(cells[1])
            if own != said:
                differ.append(f"{target}: index {sorted(said)}, folder {sorted(own)}")
    assert not differ, "docs/results/README.md's statuses differ from the folders':\n" + "\n".join(differ)


def test_the_status_check_reads_statuses() -> None:
    assert _status_words("current, partial (CPU only)") == {"current", "partial"}
    assert _status_words("current (some files superseded)") == {"current"}
    assert _status_words("superseded (`ref2/`) / rejected variant (`ref1/`)") == {"superseded", "rejected"}
    assert _status_words("**current, not re-measured**") == {"current", "not re-measured"}


def test_auto_budget_in_training_md_is_the_code() -> None:
    """docs/training.md's `--cap-max auto` formula names the rule's constants, and each row of its table
    (views × W×H, SfM points, budget) is what jsgs.train.budget.auto_budget gives for that scene."""
    from jsgs.train.budget import GAUSSIANS_PER_POINT, MAX_BUDGET, PIXELS_PER_GAUSSIAN, auto_budget

    text = (ROOT / "docs" / "training.md").read_text()
    formula = r"cap_max = min\((\d+) × SfM points, training pixels / (\d+), ([\d,]+)\)"
    assert _numbers(formula, text) == [GAUSSIANS_PER_POINT, PIXELS_PER_GAUSSIAN, MAX_BUDGET]
    rows = re.findall(r"^\| [^|]*\((\d+) × (\d+)×(\d+)\) \| ([\d,]+) \|[^\n]*\| ([\d,]+) \|$", text, re.M)
    assert len(rows) >= 4, "docs/training.md: the auto budget's table is no longer found"
    bad = []
    for views, w, h, points, budget in rows:
        got = auto_budget(int(points.replace(",", "")), [(int(w), int(h))] * int(views)).cap_max
        if got != int(budget.replace(",", "")):
            bad.append(f"{views} × {w}×{h}, {points} points: {budget}, code {got:,}")
    assert not bad, "docs/training.md's auto budgets differ from the code's:\n" + "\n".join(bad)
