"""Value objects for results (tables, target verdicts, sections) and their markdown."""

from __future__ import annotations

import math
from collections.abc import Sequence

import attrs


@attrs.frozen
class Table:
    """A markdown table.

    Attributes
    ----------
    header : tuple of str
        Column titles.
    rows : tuple of tuple of str
        Cells, already formatted; every row has ``len(header)`` cells.
    caption : str
        Text printed above the table.
    """

    header: tuple[str, ...]
    rows: tuple[tuple[str, ...], ...]
    caption: str = ""

    def __attrs_post_init__(self) -> None:
        for row in self.rows:
            if len(row) != len(self.header):
                raise ValueError(f"row {row!r} has {len(row)} cells, header {len(self.header)}")

    def markdown(self) -> str:
        """The table as GitHub-flavoured markdown."""
        lines = [f"**{self.caption}**", ""] if self.caption else []
        lines.append("| " + " | ".join(self.header) + " |")
        lines.append("|" + "|".join("---" for _ in self.header) + "|")
        lines += ["| " + " | ".join(row) + " |" for row in self.rows]
        return "\n".join(lines)


@attrs.frozen
class TargetCheck:
    """A target of issue 6 and how far it is met.

    Attributes
    ----------
    target : str
        The goal, e.g. ``"so(3) midpoint >= 200 000 steps/s"``.
    measured : str
        What was measured.
    met : bool or None
        ``None`` when it could not be measured (skipped).
    gap : str
        How far from the goal (empty when met).
    limit : str
        What limits it (or why it is met).
    """

    target: str
    measured: str
    met: bool | None
    gap: str = ""
    limit: str = ""

    @property
    def verdict(self) -> str:
        """``met``, ``not met`` or ``not measured``."""
        return {True: "met", False: "not met", None: "not measured"}[self.met]

    def markdown(self) -> str:
        """One bullet: verdict, target, measurement, gap and what limits it."""
        text = f"- **{self.verdict}** — {self.target}: measured {self.measured}"
        details = "; ".join(part for part in (self.gap, self.limit) if part)
        return text + (f" ({details})." if details else ".")


@attrs.frozen
class Section:
    """The results of one benchmark: tables, target verdicts, figures and notes."""

    title: str
    intro: str
    tables: tuple[Table, ...] = ()
    targets: tuple[TargetCheck, ...] = ()
    images: tuple[tuple[str, str], ...] = ()
    notes: tuple[str, ...] = ()
    seconds: float = 0.0

    def markdown(self) -> str:
        """The section with a level-2 heading."""
        parts = [f"## {self.title}", "", self.intro, ""]
        for alt, path in self.images:
            parts += [f"![{alt}]({path})", ""]
        for table in self.tables:
            parts += [table.markdown(), ""]
        if self.targets:
            parts += [target.markdown() for target in self.targets]
            parts.append("")
        parts += [f"- {note}" for note in self.notes]
        if self.notes:
            parts.append("")
        parts += [f"*Section time: {self.seconds:.1f} s.*", ""]
        return "\n".join(parts)


def ratio(baseline: float, candidate: float) -> str:
    """``baseline / candidate`` as ``"3.2×"`` (how many times faster the candidate is)."""
    if not (0 < candidate < math.inf and 0 < baseline < math.inf):
        return "n/a"
    value = baseline / candidate
    return f"{value:.0f}×" if value >= 100 else f"{value:.2f}×" if value < 10 else f"{value:.1f}×"


def seconds(value: float) -> str:
    """Seconds with a unit that keeps three significant digits."""
    if value >= 1:
        return f"{value:.3g} s"
    if value >= 1e-3:
        return f"{value * 1e3:.3g} ms"
    return f"{value * 1e6:.3g} µs"


def mebibytes(value: float) -> str:
    """Bytes as MiB."""
    return f"{value / 2**20:.2f} MiB"


def rate(value: float) -> str:
    """A rate with thousands separators."""
    return f"{value:,.0f}"


def render(
    header: str, targets: Sequence[TargetCheck], sections: Sequence[Section], footer: str = ""
) -> str:
    """The whole page: header, the summary of all targets, then every section."""
    lines = [header, "", "## Targets at a glance", ""]
    lines += [target.markdown() for target in targets]
    lines.append("")
    for section in sections:
        lines.append(section.markdown())
    if footer:
        lines += [footer, ""]
    return "\n".join(lines).rstrip() + "\n"
