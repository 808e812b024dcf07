"""The Markdown / JSON report of a run: table, per-group summary, headline."""
from __future__ import annotations

import math

from .framework import RAISES, Row


# ---- report ------------------------------------------------------------------------------------
def _fmt(x) -> str:
    if x is None or (isinstance(x, float) and math.isnan(x)):
        return "-"
    if isinstance(x, float):
        return "0" if x == 0 else f"{x:.1e}"
    return str(x)


def markdown(rows: list[Row], meta: dict) -> str:
    lines = [f"# clrf numerical stability ({'quick' if meta['quick'] else 'full'} run)", "",
             f"Device: {meta['device']}  ", f"Platform: {meta['platform']}  ",
             f"Date: {meta['date']}, {meta['seconds']:.0f} s", "",
             f"Rows: {len(rows)}, failed: {sum(not r.passed and not r.known_bug for r in rows)}, "
             f"failed in known-bug cases (xfail): {sum(not r.passed and r.known_bug for r in rows)}"
             f", non-finite values: {sum(r.nonfinite for r in rows)}", "",
             "max rel is normwise (max |err| / max |reference|); usage = max |err| / (atol + "
             "rtol |reference|), <= 1 passes.", "",
             summary(rows), "",
             "| group | case | quantity | max abs | max rel | tolerance (atol, rtol) | usage | "
             "non-finite | ok | note |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        t = r.tol if math.isnan(r.atol) else f"{r.tol} ({_fmt(r.atol)}, {_fmt(r.rtol)})"
        lines.append(f"| {r.group} | {r.case} | {r.quantity} | {_fmt(r.max_abs)} | "
                     f"{_fmt(r.max_rel)} | {t} | {_fmt(r.usage)} | {r.nonfinite} | "
                     f"{'yes' if r.passed else ('xfail' if r.known_bug else '**NO**')} | "
                     f"{r.note.replace('|', '/')} |")
    return "\n".join(lines) + "\n"


REL_SUMMARY_FLOOR = 1e-6


def summary(rows: list[Row]) -> str:
    """Per-group Markdown summary: worst usage and relative error, non-finite count, failures."""
    lines = ["| group | cases | checks | worst usage (case: quantity) | largest max rel (*) | "
             "non-finite | failed | known-bug (xfail) |", "|---|---|---|---|---|---|---|---|"]
    for grp in dict.fromkeys(r.group for r in rows):
        rr = [r for r in rows if r.group == grp]
        num = [r for r in rr if not math.isnan(r.max_abs) and r.tol != RAISES.name
               and not r.known_bug]
        w = max(num, key=lambda r: r.usage, default=None)
        rel = max((r.max_rel for r in num if math.isfinite(r.max_rel)
                   and r.ref_max >= REL_SUMMARY_FLOOR), default=math.nan)
        lines.append(
            f"| {grp} | {len(set(r.case for r in rr))} | {len(rr)} | "
            f"{_fmt(w.usage) + f' ({w.case}: {w.quantity})' if w else '-'} | {_fmt(rel)} | "
            f"{sum(r.nonfinite for r in rr)} | {sum(not r.passed and not r.known_bug for r in rr)}"
            f" | {sum(not r.passed and r.known_bug for r in rr)} |")
    lines.append(f"\n(*) over checks whose reference values reach {REL_SUMMARY_FLOOR:g} (a "
                 "relative error of values that are zero up to roundoff, e.g. the density "
                 "gradient behind an opaque sample, ~1e-40, says nothing).")
    return "\n".join(lines) + "\n"


def headline(rows: list[Row]) -> dict:
    num = [r for r in rows if not math.isnan(r.max_abs) and r.tol != RAISES.name
           and not r.known_bug]
    worst = max(num, key=lambda r: r.usage, default=None)
    return {"rows": len(rows), "failed": sum(not r.passed and not r.known_bug for r in rows),
            "known_bug_rows_failed": sum(not r.passed and r.known_bug for r in rows),
            "nonfinite": sum(r.nonfinite for r in rows),
            "worst_usage": (worst.case, worst.quantity, worst.usage) if worst else None}
