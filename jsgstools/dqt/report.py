"""Reports over several files: the summary, the --json document and the text table of inspect-dqt."""

from __future__ import annotations

import json
import os
from collections import Counter
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

from jsgs import __version__
from jsgs.base.errors import JsgsError
from jsgs.base.io import read_regular_bytes
from jsgstools.dqt.analysis import Analysis, analyze_bytes
from jsgstools.dqt.header import JpegHeader
from jsgstools.dqt.markers import TABLE_ORDER_NOTE
from jsgstools.dqt.parser import read_header

# --------------------------------------------------------------------------------------------------------
# Reports over several files (the CLI's logic)


@dataclass
class Inspection:
    """Result of inspecting several files: headers of the good ones, one-line errors of the bad ones,
    in the order given."""

    results: list[tuple[str, JpegHeader | JsgsError]]
    #: With --analyze: per good file's path, its Analysis, or the one-line reason it could not be analysed.
    analyses: dict[str, Analysis | JsgsError] | None = None

    @property
    def headers(self) -> list[JpegHeader]:
        return [h for _, h in self.results if isinstance(h, JpegHeader)]

    @property
    def errors(self) -> list[JsgsError]:
        return [e for _, e in self.results if isinstance(e, JsgsError)]

    def summary(self) -> dict[str, Any]:
        """Counts of files and errors, the quality range, how many tables are exactly IJG, sampling kinds."""
        hs = self.headers
        qs = [h.quality for h in hs if h.quality is not None]
        extra: dict[str, Any] = {}
        if self.analyses is not None:
            extra["double_compressed"] = sum(
                isinstance(a, Analysis) and a.double_compressed for a in self.analyses.values()
            )
        return {
            "files": len(self.results),
            "ok": len(hs),
            "errors": len(self.errors),
            "quality_min": min((q.quality for q in qs), default=None),
            "quality_max": max((q.quality for q in qs), default=None),
            "quality_exact": sum(q.exact for q in qs),
            "sampling": dict(sorted(Counter(h.sampling for h in hs).items())),
            "frames": dict(sorted(Counter(h.frame_name for h in hs).items())),
            **extra,
        }

    def to_json(self) -> dict[str, Any]:
        """The whole ``--json`` document (``jsgs/schemas/dqt_report.schema.json``)."""
        files: list[dict[str, Any]] = []
        for path, res in self.results:
            if isinstance(res, JpegHeader):
                entry = {"ok": True, **res.to_json()}
                if self.analyses is not None:
                    a = self.analyses[path]
                    entry["analysis"] = a.to_json() if isinstance(a, Analysis) else None
                    if isinstance(a, JsgsError):
                        entry["warnings"] = [*entry["warnings"], f"analysis: {a}"]
                files.append(entry)
            else:
                files.append({"ok": False, "path": path, "error": str(res)})
        return {
            "format": "jsgs-dqt-report",
            "format_version": 1,
            "tool": {"name": "jsgstools", "command": "inspect-dqt", "version": __version__},
            "table_order": "natural-row-major",
            "table_order_note": TABLE_ORDER_NOTE,
            "files": files,
            "summary": self.summary(),
        }


def dumps_json(doc: Any, indent: int = 1, _level: int = 0) -> str:
    """JSON text like ``json.dumps(doc, indent=indent)`` but with lists of numbers on one line, so an 8x8
    table reads as 8 rows."""
    pad, inner = " " * (indent * _level), " " * (indent * (_level + 1))
    if isinstance(doc, dict) and doc:
        items = [f"{inner}{json.dumps(k)}: {dumps_json(v, indent, _level + 1)}" for k, v in doc.items()]
        return "{\n" + ",\n".join(items) + "\n" + pad + "}"
    if isinstance(doc, list) and doc and not all(isinstance(x, (int, float)) for x in doc):
        items = [f"{inner}{dumps_json(v, indent, _level + 1)}" for v in doc]
        return "[\n" + ",\n".join(items) + "\n" + pad + "]"
    return json.dumps(doc)


def _analyze(path: str, header: JpegHeader) -> Analysis | JsgsError:
    """Decode and analyse one file whose header parsed (reads the whole file)."""
    try:
        return analyze_bytes(read_regular_bytes(path), header)
    except OSError as e:
        return JsgsError(f"{path}: cannot read: {e.strerror or e}")
    except JsgsError as e:
        return e
    except Exception as e:  # a bug: one line, other files go on
        return JsgsError(f"{path}: internal error in --analyze ({type(e).__name__}: {e}); please report")


def inspect_files(paths: Iterable[str | os.PathLike[str]], analyze: bool = False) -> Inspection:
    """Read every header (and with ``analyze`` decode and analyse every good file); a bad file becomes its
    JsgsError in the results instead of stopping the run."""
    results: list[tuple[str, JpegHeader | JsgsError]] = []
    for p in paths:
        name = str(p)
        try:
            results.append((name, read_header(p)))
        except JsgsError as e:
            results.append((name, e))
        except Exception as e:  # a bug (the fuzz test says there is none): still one line, other files go on
            results.append(
                (name, JsgsError(f"{name}: internal error ({type(e).__name__}: {e}); please report"))
            )
    analyses = None
    if analyze:
        analyses = {name: _analyze(name, h) for name, h in results if isinstance(h, JpegHeader)}
    return Inspection(results, analyses)


def _quality_text(h: JpegHeader) -> str:
    if h.quality is None:
        return "-"
    return f"{h.quality.quality}" if h.quality.exact else f"~{h.quality.quality}"


def _tables_text(h: JpegHeader) -> str:
    parts = []
    for t, names in h.table_uses():
        users = ",".join(names) or "unused"
        bits = "" if t.precision == 8 else "(16-bit)"
        parts.append(f"{t.id}{bits}:{users}")
    return " ".join(parts) or "-"


def _double_text(a: Analysis | JsgsError) -> str:
    if isinstance(a, JsgsError):
        return "?"
    verdict = f"yes q{a.primary_quality}" if a.double_compressed else "no"
    return f"{verdict} ({a.confidence:.2f})"


def _psnr_text(a: Analysis | JsgsError) -> str:
    if isinstance(a, JsgsError):
        return "?"
    p = a.psnr_estimate
    return "-" if p is None else f"{p:.1f} dB"


def _blocks_text(a: Analysis | JsgsError) -> str:
    if isinstance(a, JsgsError):
        return "?"
    return "-" if a.blockiness is None else f"{a.blockiness:.2f}"


def format_table(ins: Inspection, show_tables: bool = False, analyze: bool = False) -> str:
    """Human-readable report: one row per good file, then a summary line (and the 8x8 tables on request).
    With ``analyze`` (and analyses present) a DOUBLE column: "no" or "yes qNN", and the confidence; and EST.
    PSNR: the PSNR against the uncompressed original that the estimated quantisation noise implies; BLOCKS:
    how much the decoded luma's 8x8 block grid shows (about 1 where it does not)."""
    head: tuple[str, ...] = (
        "FILE",
        "SIZE",
        "FRAME",
        "COLOR",
        "SAMPLING",
        "QUALITY",
        "TABLES (id:components)",
        "DRI",
    )
    with_double = analyze and ins.analyses is not None
    if with_double:
        head = (*head, "DOUBLE (confidence)", "EST. PSNR", "BLOCKS")
    rows = [
        (
            h.path,
            f"{h.width}x{h.height}",
            h.frame_name if h.sample_precision == 8 else f"{h.frame_name} {h.sample_precision}-bit",
            h.color_space,
            h.sampling,
            _quality_text(h),
            _tables_text(h),
            str(h.restart_interval) if h.restart_interval else "-",
            *(
                (
                    _double_text(ins.analyses[h.path]),
                    _psnr_text(ins.analyses[h.path]),
                    _blocks_text(ins.analyses[h.path]),
                )
                if with_double and ins.analyses is not None
                else ()
            ),
        )
        for h in ins.headers
    ]
    lines: list[str] = []
    if rows:
        widths = [max(len(str(x)) for x in col) for col in zip(head, *rows, strict=True)]
        for row in (head, *rows):
            lines.append("  ".join(str(x).ljust(w) for x, w in zip(row, widths, strict=True)).rstrip())
    s = ins.summary()
    if rows:
        lines.append("")
    errors = f"{s['errors']} error" + ("" if s["errors"] == 1 else "s")
    lines.append(f"summary: {s['files']} file{'' if s['files'] == 1 else 's'}, {s['ok']} ok, {errors}")
    if s["quality_min"] is not None:
        n_q = sum(1 for h in ins.headers if h.quality is not None)
        q_range = f"{s['quality_min']}" + (
            "" if s["quality_min"] == s["quality_max"] else f"..{s['quality_max']}"
        )
        note = "" if s["quality_exact"] == n_q else "; ~Q: not IJG's tables, Q is the closest IJG quality"
        lines.append(f"  IJG quality  {q_range} ({s['quality_exact']} of {n_q} exact{note})")
    if s["sampling"]:
        lines.append("  sampling     " + ", ".join(f"{k} x{v}" for k, v in s["sampling"].items()))
    if s["frames"]:
        lines.append("  frames       " + ", ".join(f"{k} x{v}" for k, v in s["frames"].items()))
    if with_double and ins.analyses is not None:
        failed = [a for a in ins.analyses.values() if isinstance(a, JsgsError)]
        note = f" ({len(failed)} not analysed, see warnings)" if failed else ""
        lines.append(
            f"  double       {s['double_compressed']} of {len(ins.analyses)} double-compressed{note}"
        )
        for a in failed:
            lines.append(f"  warning: {a}")
    if show_tables:
        for h in ins.headers:
            uses = h.table_uses()
            for t, names in uses:
                lines.append("")
                users = f" for {','.join(names)}" if len(uses) > len(h.tables) else ""  # an id listed twice
                lines.append(f"{h.path}: table {t.id}{users} ({t.precision}-bit), natural row-major [v][u]:")
                width = max(len(str(int(x))) for x in t.values.flat)
                for row in t.values:
                    lines.append("  " + " ".join(str(int(x)).rjust(width) for x in row))
    return "\n".join(lines)
