"""`opnav --help` starts fast: the parser is built without the heavy modules (a property, not a timing)."""

import importlib
import pkgutil
import subprocess
import sys

import pytest

import opnav.commands
from opnav.cli import build_parser, command_named, commands

#: Modules `import opnav.cli` and building the top-level parser must not import.
HEAVY = ("ccsds_ndm", "matplotlib", "dask", "scipy.stats", "astropy", "numba", "opnav.studies", "opnav.filters")


def _imported_after(code: str) -> set[str]:
    """The modules a fresh interpreter has imported after running ``code``."""
    probe = f"import sys\n{code}\nprint('\\n'.join(sorted(sys.modules)))"
    result = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True)
    return set(result.stdout.split())


@pytest.mark.parametrize("code", [
    "import opnav.cli",
    "from opnav.cli import build_parser; build_parser(load=())",
    "from opnav.cli import main\ntry:\n    main(['--version'])\nexcept SystemExit:\n    pass",
    "import contextlib, io\nfrom opnav.cli import main\nwith contextlib.redirect_stdout(io.StringIO()):\n"
    "    try:\n        main(['--help'])\n    except SystemExit:\n        pass",
])
def test_the_top_level_parser_imports_no_heavy_module(code):
    modules = _imported_after(code)
    heavy = sorted(m for m in modules if any(m == h or m.startswith(h + ".") for h in HEAVY))
    assert heavy == []
    assert not any(m.startswith("opnav.commands.") for m in modules)


def test_a_command_imports_only_its_own_module():
    modules = _imported_after("from opnav.cli import build_parser; build_parser(load=('run',))")
    commands = sorted(m for m in modules if m.startswith("opnav.commands."))
    assert commands == ["opnav.commands.run"]


def test_the_command_table_read_from_the_sources_is_what_the_modules_say():
    modules = sorted(m.name for m in pkgutil.iter_modules(opnav.commands.__path__) if not m.name.startswith("_"))
    assert [c.name for c in commands()] == modules
    for command in commands():
        module = importlib.import_module(command.module)
        assert (module.NAME, module.HELP, getattr(module, "OUT", "folder")) == (command.name, command.help, command.out)
    assert {c.name: c.out for c in commands()}["process"] == "file"


def test_every_command_gets_its_options_when_loaded():
    choices = build_parser()._subparsers._group_actions[0].choices
    for command in commands():
        options = {s for action in choices[command.name]._actions for s in action.option_strings}
        assert "--help" in options
        assert len(options) > 1, command.name


@pytest.mark.parametrize("argv, name", [
    (["run", "x.toml", "--out", "o"], "run"), (["-v", "navigate", "m.csv"], "navigate"), (["--version"], None),
    (["--help"], None), ([], None), (["nosuch", "run"], None), (["--", "run"], None),
])
def test_the_command_is_the_first_word_that_is_not_an_option(argv, name):
    assert command_named(argv) == name


@pytest.mark.parametrize("name", ["navigate", "run"])
def test_the_navigate_and_run_parsers_import_no_numerical_module(name):
    """``opnav navigate --help`` and ``opnav run --help`` build their parser from light modules only
    (the filter names and option classes are in :mod:`opnav.filters.option_types`)."""
    modules = _imported_after(f"from opnav.cli import build_parser; build_parser(load=({name!r},))")
    numerical = ("numpy", "scipy", "astropy", "numba", "filterpy", "matplotlib")
    assert sorted(m for m in modules if m.split(".")[0] in numerical) == []
