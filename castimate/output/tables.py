"""Rows of plain values (one dict per row) as CSV text: the tables of the scale-out verbs."""

from __future__ import annotations

import csv
import io


def csv_text(rows: list[dict]) -> str:
    """CSV with a header of the first row's keys (empty text for no rows); None is an empty cell."""
    if not rows:
        return ""
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=list(rows[0]), lineterminator="\n")
    w.writeheader()
    w.writerows([{k: ("" if v is None else v) for k, v in r.items()} for r in rows])
    return buf.getvalue()
