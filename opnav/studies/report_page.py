"""One report page: ``report.md``, a self-contained ``report.html`` and ``figures/<id>.png``.

Every report opnav writes (a study run, S2/S4, a campaign) is a title, a sequence of blocks and a
provenance block, written by :func:`write_page`:

- a ``str`` block is short Markdown: ``#`` headings, paragraphs, ``- `` bullets, pipe tables
  (first row the header) and inline ```code```;
- a :class:`Table` is a titled table with an optional note (a paper table's citation);
- a :class:`Figure` is a PNG with a stable id and a one-sentence caption: ``figures/<id>.png`` on
  disk, ``<figure id="fig-<id>">`` in the HTML (base64-inlined, so the page travels alone).

:func:`provenance` records what made the page: the command line, the run file and its SHA-256, opnav's
version, the git revision of the opnav checkout (None for an installed wheel), the date (UTC) and the
machine. Every file is written atomically.
"""

from __future__ import annotations

import base64
import html
import os
import platform
import re
import shlex
import subprocess
import sys
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import Sequence

from .. import __version__
from ..files import atomic_write_bytes, atomic_write_text
from ..records import file_sha256

_ID = re.compile(r"[a-z0-9_]+")
_FIGURE_LINK = re.compile(r"!\[[^\]]*\]\(figures/([a-z0-9_]+)\.png\)")


def figure_id(name: str) -> str:
    """``name`` (e.g. a filter's, ``sr-ukf``) as a part of a figure id: lower case, ``-`` and other signs as ``_``."""
    return "".join(c if c.isalnum() else "_" for c in name.lower())


@dataclass(frozen=True)
class Figure:
    """A report figure.

    Attributes
    ----------
    id : str
        Stable name, ``[a-z0-9_]+``: saved as ``figures/<id>.png``, ``<figure id="fig-<id>">`` in the HTML.
    caption : str
        One sentence: what is plotted and what to look for.
    png : bytes
        The PNG image.
    """

    id: str
    caption: str
    png: bytes

    def __post_init__(self) -> None:
        if not _ID.fullmatch(self.id):
            raise ValueError(f"figure id {self.id!r}: use lower-case letters, digits and '_' only")


@dataclass(frozen=True)
class Table:
    """A report table: ``title``, ``header`` (column names with their units), ``rows`` of text cells
    (each as long as ``header``) and a ``note`` printed under it (e.g. the citation of a paper table)."""

    title: str
    header: tuple[str, ...]
    rows: tuple[tuple[str, ...], ...]
    note: str = ""

    def __post_init__(self) -> None:
        for row in self.rows:
            if len(row) != len(self.header):
                raise ValueError(f"table {self.title!r}: a row has {len(row)} cells for {len(self.header)} columns")


@dataclass(frozen=True)
class Provenance:
    """What made a report.

    Attributes
    ----------
    command : str or None
        The command line, shell-quoted (None when the report was made from Python).
    run_file : str or None
        The run file's path as given.
    run_file_sha256 : str or None
        SHA-256 of the run file's bytes when the report was written (None without a run file).
    opnav_version : str
    git_revision : str or None
        ``HEAD`` of the git checkout opnav was imported from; None when opnav is not in one (a wheel).
    git_modified : bool or None
        Whether that checkout's tracked files differ from ``HEAD`` (None without a checkout).
    date_utc : str
        When the provenance was taken, ISO 8601 UTC to the second.
    machine : str
        Platform, Python version and the cores this process may use.
    """

    command: str | None
    run_file: str | None
    run_file_sha256: str | None
    opnav_version: str
    git_revision: str | None
    git_modified: bool | None
    date_utc: str
    machine: str

    def rows(self) -> tuple[tuple[str, str], ...]:
        """(item, value) text rows for the provenance table."""
        revision = "not a git checkout"
        if self.git_revision is not None:
            revision = self.git_revision + (" (with uncommitted changes)" if self.git_modified else "")
        return (("command", self.command or "not run from the command line"),
                ("run file", self.run_file or "none"),
                ("run file SHA-256", self.run_file_sha256 or "-"),
                ("opnav version", self.opnav_version),
                ("git revision", revision),
                ("date (UTC)", self.date_utc),
                ("machine", self.machine))


def _git(*args: str) -> str | None:
    """Output of ``git args`` in opnav's package folder, stripped; None when git fails or is missing."""
    try:
        done = subprocess.run(["git", "-C", str(Path(__file__).resolve().parents[1]), *args],
                              capture_output=True, text=True, timeout=10, check=False)
    except (OSError, subprocess.SubprocessError):
        return None
    return done.stdout.strip() if done.returncode == 0 else None


def _git_revision() -> tuple[str | None, bool | None]:
    """(HEAD, modified) of the checkout opnav is imported from, or (None, None)."""
    top = _git("rev-parse", "--show-toplevel")
    package = Path(__file__).resolve().parents[1]
    # opnav installed inside some other repository (a venv in a user's project) is not that checkout
    if top is None or Path(top).resolve() != package.parent:
        return None, None
    revision = _git("rev-parse", "HEAD")
    if revision is None:
        return None, None
    status = _git("status", "--porcelain", "--untracked-files=no")
    return revision, None if status is None else bool(status)


def _cores() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not Linux
        return os.cpu_count() or 1


def provenance(command: Sequence[str] | None, run_file: str | Path | None) -> Provenance:
    """The :class:`Provenance` of a report made now by ``command`` (its argv, e.g. ``sys.argv``; None
    from Python) from ``run_file`` (None: no run file)."""
    revision, modified = _git_revision()
    python = ".".join(str(v) for v in sys.version_info[:3])
    return Provenance(
        command=None if command is None else shlex.join(str(a) for a in command),
        run_file=None if run_file is None else str(run_file),
        run_file_sha256=None if run_file is None else file_sha256(run_file),
        opnav_version=__version__, git_revision=revision, git_modified=modified,
        date_utc=datetime.now(timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ"),
        machine=f"{platform.platform()}, Python {python}, {_cores()} cores")


def provenance_table(prov: Provenance) -> Table:
    """The provenance as a two-column :class:`Table`."""
    return Table("Provenance", ("item", "value"), prov.rows())


# --- Markdown ---------------------------------------------------------------------------------------

def _md_cell(text: str) -> str:
    return str(text).replace("|", "\\|").replace("\n", " ")


def table_markdown(table: Table) -> list[str]:
    """Markdown lines of ``table``: its title as a heading, a pipe table, the note as a paragraph."""
    lines = [f"### {table.title}", "", "| " + " | ".join(_md_cell(c) for c in table.header) + " |",
             "|" + "---|" * len(table.header)]
    lines += ["| " + " | ".join(_md_cell(c) for c in row) + " |" for row in table.rows]
    if table.note:
        lines += ["", table.note]
    return lines + [""]


def _page_markdown(title: str, blocks: Sequence[str | Table | Figure], prov: Provenance) -> str:
    lines = [f"# {title}", ""]
    for block in blocks:
        if isinstance(block, Table):
            lines += table_markdown(block)
        elif isinstance(block, Figure):
            lines += [f"![{block.id}](figures/{block.id}.png)", "", f"*Figure {block.id}*: {block.caption}", ""]
        else:
            lines += [str(block), ""]
    lines += ["## Provenance", ""] + table_markdown(provenance_table(prov))[2:]
    return "\n".join(lines).rstrip("\n") + "\n"


# --- HTML -------------------------------------------------------------------------------------------

_CODE = re.compile(r"`([^`]+)`")
_BOLD = re.compile(r"\*\*([^*]+)\*\*")
_ITALIC = re.compile(r"(?<![*\w])\*([^*]+)\*(?![*\w])")


def inline_html(text: str) -> str:
    """HTML of one line of Markdown text: escaped, with ```code```, ``**bold**`` and ``*italic*``."""
    escaped = html.escape(text, quote=False)
    escaped = _CODE.sub(r"<code>\1</code>", escaped)
    escaped = _BOLD.sub(r"<strong>\1</strong>", escaped)
    return _ITALIC.sub(r"<em>\1</em>", escaped)


def _split_row(text: str) -> list[str]:
    # cells split on '|' not escaped as '\|'
    cells = re.split(r"(?<!\\)\|", text.strip().strip("|"))
    return [c.strip().replace("\\|", "|") for c in cells]


def markdown_html(lines: Sequence[str]) -> str:
    """HTML of simple Markdown ``lines``: headings, pipe tables (first row the header), ``- `` bullets,
    paragraphs (consecutive text lines joined) and inline code, bold and italic."""
    body: list[str] = []
    table: list[list[str]] = []
    items: list[str] = []
    para: list[str] = []

    def flush() -> None:
        if table:
            rows = [r for r in table if not all(set(c) <= set("-: ") for c in r)]
            body.append("<table>" + "".join(
                "<tr>" + "".join(f"<{tag}>{inline_html(c)}</{tag}>" for c in r) + "</tr>"
                for r, tag in zip(rows, ["th"] + ["td"] * len(rows))) + "</table>")
            table.clear()
        if items:
            body.append("<ul>" + "".join(f"<li>{inline_html(i)}</li>" for i in items) + "</ul>")
            items.clear()
        if para:
            body.append(f"<p>{inline_html(' '.join(para))}</p>")
            para.clear()

    for line in lines:
        text = line.strip()
        if text.startswith("|"):
            if items or para:
                flush()
            table.append(_split_row(text))
        elif text.startswith("- "):
            if table or para:
                flush()
            items.append(text[2:])
        elif text.startswith("#"):
            flush()
            level = min(len(text) - len(text.lstrip("#")), 6)
            body.append(f"<h{level}>{inline_html(text[level:].strip())}</h{level}>")
        elif text:
            if table or items:
                flush()
            para.append(text)
        else:
            flush()
    flush()
    return "".join(body)


def table_html(table: Table) -> str:
    """HTML of ``table``: a heading, the table and its note."""
    head = "".join(f"<th>{html.escape(c, quote=False)}</th>" for c in table.header)
    rows = "".join("<tr>" + "".join(f"<td>{html.escape(c, quote=False)}</td>" for c in row) + "</tr>" for row in table.rows)
    note = f"<p class='note'>{inline_html(table.note)}</p>" if table.note else ""
    return f"<h3>{html.escape(table.title)}</h3><table><tr>{head}</tr>{rows}</table>{note}"


def figure_html(figure: Figure) -> str:
    """HTML of ``figure``: the PNG inlined (base64) with its caption."""
    data = base64.b64encode(figure.png).decode()
    return (f"<figure id='fig-{figure.id}'><img alt='{html.escape(figure.caption)}' src='data:image/png;base64,{data}'>"
            f"<figcaption><b>{figure.id}</b>: {inline_html(figure.caption)}</figcaption></figure>")


_STYLE = ("body{font-family:sans-serif;margin:1.5em auto;max-width:1400px;padding:0 1em;line-height:1.35}"
          "table{border-collapse:collapse;margin:0.5em 0 1em;max-width:100%}"
          "td,th{border:1px solid #ccc;padding:3px 8px;font-size:13px;text-align:left;vertical-align:top;"
          "overflow-wrap:anywhere;min-width:3em}"  # a long value (a path) wraps in its cell, a short word stays wholeth{background:#f2f2f2}"
          "figure{margin:1.5em 0}img{max-width:100%;height:auto}figcaption{font-size:13px;color:#333}"
          "p.note{font-size:12px;color:#555;margin-top:-0.5em}code{font-size:12px}"
          "#provenance td{font-family:monospace;font-size:12px;word-break:break-all}")


def _page_html(title: str, blocks: Sequence[str | Table | Figure], prov: Provenance) -> str:
    parts = [f"<h1>{html.escape(title)}</h1>"]
    for block in blocks:
        if isinstance(block, Table):
            parts.append(table_html(block))
        elif isinstance(block, Figure):
            parts.append(figure_html(block))
        else:
            parts.append(markdown_html(str(block).splitlines()))
    prov_rows = "".join(f"<tr><th>{html.escape(k, quote=False)}</th><td>{html.escape(v, quote=False)}</td></tr>" for k, v in prov.rows())
    parts.append(f"<section id='provenance'><h2>Provenance</h2><table>{prov_rows}</table></section>")
    return (f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>{html.escape(title)}</title>"
            f"<style>{_STYLE}</style></head><body>" + "".join(parts) + "</body></html>\n")


def write_page(out: Path, title: str, blocks: Sequence[str | Table | Figure], prov: Provenance, *,
               name: str = "report") -> None:
    """Write ``out/<name>.md``, the self-contained ``out/<name>.html`` and ``out/figures/<id>.png``
    (the figures the page's earlier version linked and this one does not are removed).

    Parameters
    ----------
    out : Path
        Folder (created).
    title : str
        The page's title (its first heading).
    blocks : sequence of str, Table or Figure
        The page in order (module notes); figure ids must be unique.
    prov : Provenance
        Printed last, in ``<section id="provenance">``.
    name : str
        File stem of the page (``report``; a campaign writes ``campaign``).
    """
    out = Path(out)
    figures = [b for b in blocks if isinstance(b, Figure)]
    ids = [f.id for f in figures]
    if len(set(ids)) != len(ids):
        raise ValueError(f"figure ids repeat in {title!r}: {sorted(i for i in set(ids) if ids.count(i) > 1)}")
    if figures:
        (out / "figures").mkdir(parents=True, exist_ok=True)
    for figure in figures:
        atomic_write_bytes(out / "figures" / f"{figure.id}.png", figure.png)
    # the figures an earlier version of this page linked and this one has no more would read as its
    # own; other pages' figures in the folder are left alone
    try:
        earlier = set(_FIGURE_LINK.findall((out / f"{name}.md").read_text()))
    except (OSError, UnicodeDecodeError):
        earlier = set()
    for stale in sorted(earlier - set(ids)):
        (out / "figures" / f"{stale}.png").unlink(missing_ok=True)
    atomic_write_text(out / f"{name}.md", _page_markdown(title, blocks, prov))
    atomic_write_text(out / f"{name}.html", _page_html(title, blocks, prov))
