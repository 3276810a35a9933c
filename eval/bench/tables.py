"""The results' tables: a pandas DataFrame with a name (file stem), a title and notes, written as
CSV and Markdown by pandas (``DataFrame.to_csv``, ``DataFrame.to_markdown`` through tabulate), and
the number format of their cells (``fmt``)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import pandas as pd

#: What a table cell shows for a missing figure.
MISSING = "–"


def fmt(v, nd: int = 3, scale: float = 1.0) -> str:
    """A figure as table text: ``nd`` decimals after ``scale``; integers as they are; None, NaN -> '–'."""
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return MISSING
    if isinstance(v, (int, np.integer)) and scale == 1.0:
        return str(int(v))
    return f"{float(v) * scale + 0.0:.{nd}f}".replace("-0." + "0" * nd, "0." + "0" * nd)


def rule_label(kind: str, rule: str | None) -> str:
    """The '2D rule' cell of a prediction set: a 2D detector's own, or a 3D method's projection rule."""
    if kind == "2d":
        return "2D detector"
    return "paper's projection" if rule == "paper" else "exact silhouette"


@dataclass
class Table:
    """A results table: ``frame`` (the cells as text, one column per heading), a file stem, a title
    and the notes printed under it."""

    name: str
    title: str
    columns: list[str]
    rows: list[list]
    notes: list[str] = field(default_factory=list)

    @property
    def frame(self) -> pd.DataFrame:
        return pd.DataFrame([["" if c is None else c for c in r] for r in self.rows], columns=self.columns,
                            dtype=object)

    def csv(self) -> str:
        return self.frame.to_csv(index=False, lineterminator="\n")

    def markdown(self, heading: bool = True) -> str:
        lines = [f"### {self.title}", ""] if heading else []
        # disable_numparse: the cells are already formatted text ("0.500" stays "0.500")
        lines.append(self.frame.to_markdown(index=False, tablefmt="pipe", disable_numparse=True))
        if self.notes:
            lines.append("")
            lines += [f"{n}" if n.startswith("- ") else f"- {n}" for n in self.notes]
        return "\n".join(lines) + "\n"
