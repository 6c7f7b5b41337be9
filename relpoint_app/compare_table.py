"""The table of ``relpoint compare``: text, Markdown, CSV or JSON.

Text and Markdown are for reading: one row per summary key, one column per run (runs are few, keys
many). CSV and JSON are for scripts: one row per run (``run, estimator, align`` and one column per
key). Missing values (a run without that figure) are ``-`` in text and Markdown, empty in CSV and
``null`` in JSON; undefined ones (NaN) are ``n/a`` in text and Markdown (as ``evaluate`` prints them),
empty in CSV and ``null`` in JSON (as ``evaluate --csv`` and a batch's ``results.csv`` write them). Every
form names relpoint in its first line or key, which is how a later ``compare -o`` knows it may replace
the file.
"""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Sequence
from typing import Any

import relpoint
from formats.outputs import json_text, register_csv_header_prefix
from relpoint.evaluation.comparison import ComparedRun, table_rows
from relpoint.evaluation.evaluate import COUNT_KEYS, with_counts

TABLE_FORMATS = ("text", "markdown", "csv", "json")

#: The first columns of every CSV table; the summary keys follow.
ROW_LABELS = ("run", "estimator", "align")
register_csv_header_prefix(",".join(ROW_LABELS) + ",")

#: Output suffix -> table format, for ``-o FILE`` without ``--format``.
SUFFIX_FORMATS = {".md": "markdown", ".markdown": "markdown", ".csv": "csv", ".json": "json"}


def _cell(value: float | None) -> str:
    if value is None:
        return "-"
    if math.isnan(value):
        return "n/a"
    if float(value).is_integer() and abs(value) < 1e15:
        return str(int(value))
    return f"{value:.6f}"


def _grid(runs: Sequence[ComparedRun], keys: Sequence[str]) -> list[list[str]]:
    """Header row (``key`` then run labels) and one row per label line and summary key."""
    rows = table_rows(runs, keys)
    grid = [["", *(row["run"] for row in rows)]]
    for name in ROW_LABELS[1:]:
        if any(row[name] for row in rows):
            grid.append([name, *(row[name] or "-" for row in rows)])
    grid.extend([key, *(_cell(row[key]) for row in rows)] for key in keys)
    return grid


def text_table(runs: Sequence[ComparedRun], keys: Sequence[str]) -> str:
    """Aligned columns under a ``# relpoint compare`` caption."""
    grid = _grid(runs, keys)
    widths = [max(len(row[i]) for row in grid) for i in range(len(grid[0]))]
    lines = [f"# relpoint compare: {len(runs)} run{'s' if len(runs) != 1 else ''}"]
    for row in grid:
        cells = [row[0].ljust(widths[0]), *(cell.rjust(width) for cell, width in zip(row[1:], widths[1:], strict=True))]
        lines.append("  ".join(cells).rstrip())
    return "\n".join(lines) + "\n"


def markdown_table(runs: Sequence[ComparedRun], keys: Sequence[str]) -> str:
    """A GitHub-flavoured Markdown table after a ``<!-- relpoint compare -->`` comment."""
    grid = _grid(runs, keys)

    def escape(cell: str) -> str:
        return cell.replace("|", "\\|")

    header, *body = grid
    lines = [
        "<!-- relpoint compare -->",
        "| " + " | ".join(escape(c) or "key" for c in header) + " |",
        "|---|" + "---:|" * (len(header) - 1),
    ]
    lines.extend("| " + " | ".join(escape(c) for c in row) + " |" for row in body)
    return "\n".join(lines) + "\n"


def csv_table(runs: Sequence[ComparedRun], keys: Sequence[str]) -> str:
    """One line per run; floats written with ``repr`` (round-trip exact), missing and non-finite ones empty."""
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow([*ROW_LABELS, *keys])
    for row in map(_counted_row, table_rows(runs, keys)):
        writer.writerow([*(row[name] for name in ROW_LABELS), *(_csv_cell(row[k]) for k in keys)])
    return buffer.getvalue()


def _csv_cell(value: float | None) -> str:
    return "" if value is None or not math.isfinite(value) else repr(value)


def _counted_row(row: dict[str, Any]) -> dict[str, Any]:
    """A :func:`table_rows` row with its counts as ints (a missing one stays None)."""
    return {**row, **with_counts({k: v for k, v in row.items() if k in COUNT_KEYS and v is not None})}


def json_table(runs: Sequence[ComparedRun], keys: Sequence[str]) -> str:
    """``{"relpoint_version", "columns", "runs": [{"run", "estimator", "align", "source", "summary"}]}``."""
    document = {
        "relpoint_version": relpoint.__version__,
        "columns": list(keys),
        "runs": [
            {
                "run": run.label,
                "estimator": run.estimator,
                "align": run.align,
                "source": run.source,
                "summary": {k: row[k] for k in keys},
            }
            for run, row in zip(runs, map(_counted_row, table_rows(runs, keys)), strict=True)
        ],
    }
    return json_text(document, indent=2) + "\n"


def render_table(runs: Sequence[ComparedRun], keys: Sequence[str], table_format: str) -> str:
    """The table in ``table_format`` (one of :data:`TABLE_FORMATS`)."""
    render = {"text": text_table, "markdown": markdown_table, "csv": csv_table, "json": json_table}
    return render[table_format](runs, keys)
