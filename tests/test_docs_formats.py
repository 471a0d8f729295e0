"""The file-format pages (docs/formats/) stay true: their examples load and their key tables list every key.

- Every code block marked as a complete example by an HTML comment on the line before it,
  ``<!-- example: scene -->``, ``<!-- example: navigation -->``, ``<!-- example: run -->`` (TOML)
  or ``<!-- example: records -->`` (measurement CSV), several kinds separated by spaces, is
  written to a file and loaded with the matching loader (:func:`opnav.sim.scene.load_scene`,
  :func:`opnav.filters.options.load_navigation`, :func:`opnav.studies.settings.load_run_file`,
  :func:`opnav.records.read_csv`).
- Every table marked ``<!-- keys: dotted.path.Name -->`` (optionally followed by ``-field`` for
  fields the file may not set) lists, in the backquoted names of its first column, exactly the
  init fields of that dataclass, or the items of that tuple, or the keys of that dict.
"""

from __future__ import annotations

import dataclasses
import importlib
import re
from pathlib import Path

import pytest

FORMATS = Path(__file__).resolve().parents[1] / "docs" / "formats"
README = Path(__file__).resolve().parents[1] / "README.md"
PAGES = ("README.md", "scene.md", "runfile.md", "navigation.md", "measurements.md", "frames.md", "summary.md",
         "campaign.md", "ccsds.md", "index-cache.md", "camera.md")

_EXAMPLE = re.compile(r"<!--\s*example:\s*([\w\s-]+?)\s*-->\s*\n```(toml|csv)\n(.*?)```", re.S)
_KEYS = re.compile(r"<!--\s*keys:\s*([\w.]+)((?:\s+-\w+)*)\s*-->\s*\n((?:\|.*\n?)+)")


def _load_scene(path: Path):
    from opnav.sim.scene import load_scene

    return load_scene(path)


def _load_navigation(path: Path):
    from opnav.filters.options import load_navigation

    return load_navigation(path)


def _load_run(path: Path):
    from opnav.studies.settings import load_run_file

    return load_run_file(path)


def _load_records(path: Path):
    from opnav.records import read_csv

    records = read_csv(path)
    assert records, f"{path}: no records"
    return records


LOADERS = {"scene": _load_scene, "navigation": _load_navigation, "run": _load_run, "records": _load_records}
#: The file each kind of example is written to (its suffix is what its loader expects).
SUFFIX = {"scene": ".toml", "navigation": ".toml", "run": ".toml", "records": ".csv"}


def _examples() -> list[tuple[str, int, str, str]]:
    """(page, number on the page, loader kind, TOML text) of every marked example."""
    found = []
    for page in sorted(FORMATS.glob("*.md")):
        for number, match in enumerate(_EXAMPLE.finditer(page.read_text()), start=1):
            for kind in match.group(1).split():
                found.append((page.name, number, kind, match.group(3)))
    return found


def _key_tables() -> list[tuple[str, str, tuple[str, ...], str]]:
    """(page, dotted name, excluded fields, table text) of every marked key table."""
    found = []
    for page in sorted(FORMATS.glob("*.md")):
        for match in _KEYS.finditer(page.read_text()):
            excluded = tuple(word.lstrip("-") for word in match.group(2).split())
            found.append((page.name, match.group(1), excluded, match.group(3)))
    return found


def _documented(table: str) -> list[str]:
    """The backquoted names of the first column of a Markdown table (header and rule rows skipped)."""
    names = []
    for line in table.splitlines()[2:]:
        cells = line.strip().strip("|").split("|")
        names += re.findall(r"`([^`]+)`", cells[0])
    return names


def _known(dotted: str, excluded: tuple[str, ...]) -> list[str]:
    module, _, name = dotted.rpartition(".")
    thing = getattr(importlib.import_module(module), name)
    if dataclasses.is_dataclass(thing):
        names = [f.name for f in dataclasses.fields(thing) if f.init]
    elif isinstance(thing, dict):
        names = list(thing)
    else:
        names = list(thing)
    return [n for n in names if n not in excluded]


def test_every_page_exists_and_is_linked():
    index = (FORMATS / "README.md").read_text()
    for page in PAGES:
        assert (FORMATS / page).is_file(), page
        if page != "README.md":
            assert f"]({page})" in index, f"docs/formats/README.md does not link {page}"
    assert "docs/formats/README.md" in README.read_text(), "README.md does not link docs/formats/README.md"


def test_every_loader_has_an_example():
    kinds = {kind for _, _, kind, _ in _examples()}
    assert kinds == set(LOADERS), f"examples found for {sorted(kinds)}; expected {sorted(LOADERS)}"


@pytest.mark.parametrize("page, number, kind, text", _examples(),
                         ids=[f"{p}-{n}-{k}" for p, n, k, _ in _examples()])
def test_the_example_loads(tmp_path, page, number, kind, text):
    assert kind in LOADERS, f"{page}: example {number} names an unknown loader {kind!r}"
    path = tmp_path / f"{Path(page).stem}_{number}{SUFFIX[kind]}"
    path.write_text(text)
    LOADERS[kind](path)  # raises InputError naming the key when the example has drifted


def test_key_tables_are_found():
    tables = _key_tables()
    assert len(tables) >= 28, f"only {len(tables)} marked key tables in docs/formats"


@pytest.mark.parametrize("page, dotted, excluded, table", _key_tables(),
                         ids=[f"{p}-{d.rpartition('.')[2]}" for p, d, _, _ in _key_tables()])
def test_the_key_table_lists_every_key(page, dotted, excluded, table):
    documented = _documented(table)
    known = _known(dotted, excluded)
    assert len(documented) == len(set(documented)), f"{page}: {dotted}: a key is listed twice"
    missing = [n for n in known if n not in documented]
    extra = [n for n in documented if n not in known]
    assert not missing and not extra, (f"docs/formats/{page}, table of {dotted}: undocumented {missing}, "
                                       f"documented but unknown {extra}")
