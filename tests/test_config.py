"""opnav.config, the one loader: typed tables, unknown keys with a suggestion, --set overrides,
typed filter options that fail on load, and missing files named by their kind."""

from __future__ import annotations

import dataclasses
import datetime
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest

from opnav.cli import main
from opnav.config import CalendarText, Where, build, convert, parse_overrides, read_toml
from opnav.errors import InputError
from opnav.filters.batch import BatchOptions
from opnav.filters.federated import FederatedSetup
from opnav.filters.options import NavigationConfig, load_navigation
from opnav.filters.particle import ParticleOptions
from opnav.filters.ukf import UKFOptions
from opnav.sim.scene import load_scene
from opnav.studies.settings import load_run_file

ROOT = Path(__file__).resolve().parents[1]
S1 = ROOT / "samples" / "s1_jul_both_0.1.toml"
NAVIGATION = (ROOT / "opnav" / "data" / "demo.toml").read_text()


@dataclass(frozen=True)
class Inner:
    alpha: float = 1.0
    names: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        if not self.alpha > 0.0:
            raise InputError(f"alpha must be positive, got {self.alpha}")


@dataclass(frozen=True)
class Outer:
    size: int
    when: CalendarText | None = None
    vector: tuple[float, float, float] = (0.0, 0.0, 0.0)
    flag: bool = False
    inner: Inner = field(default_factory=Inner)


def test_build_reads_a_table_by_the_type_hints_into_sub_tables():
    where = Where("f.toml", "outer")
    value = build(Outer, {"size": 3, "when": datetime.datetime(2014, 7, 15), "vector": [1, 2.5, 3],
                          "inner": {"alpha": 2, "names": ["a", "b"]}}, where)
    assert value == Outer(3, "2014-07-15 00:00:00", (1.0, 2.5, 3.0), False, Inner(2.0, ("a", "b")))
    assert isinstance(value.vector[0], float) and isinstance(value.inner.alpha, float)
    assert build(Outer, {"size": 1}, where).inner == Inner()  # an absent sub-table keeps its defaults
    with pytest.raises(InputError, match=r"^f.toml: \[outer\] needs size$"):
        build(Outer, {}, where)
    with pytest.raises(InputError, match=r"^f.toml: \[outer.inner\] alpha must be positive, got -1.0$"):
        build(Outer, {"size": 1, "inner": {"alpha": -1}}, where)
    with pytest.raises(InputError, match=r"^f.toml: \[outer\] inner must be a table \(\[outer.inner\]\), got 3$"):
        build(Outer, {"size": 1, "inner": 3}, where)
    with pytest.raises(InputError, match=r"\[outer\] vector must be an array of 3 finite numbers, got \[1, 2\]"):
        build(Outer, {"size": 1, "vector": [1, 2]}, where)


def test_toml_values_or_text_as_set_gives_them():
    where = Where("f.toml", "outer")
    # TOML values only: text is not a number or a boolean, and the message says so
    with pytest.raises(InputError, match=r"^f.toml: \[outer\] flag must be true or false \(written without "
                                         r"quotes\), got 'false'$"):
        build(Outer, {"size": 1, "flag": "false"}, where)
    with pytest.raises(InputError, match=r"\[outer\] size must be int \(a whole number\), got 1.5"):
        build(Outer, {"size": 1.5}, where)
    # text accepted (scene and run files, --set values)
    value = build(Outer, {"size": "4", "flag": "yes", "vector": "1, 2, 3", "inner": {"names": "a,b"}}, where,
                  text=True)
    assert value == Outer(4, None, (1.0, 2.0, 3.0), True, Inner(1.0, ("a", "b")))
    for bad in ("nan", "1e999", "big", True):
        with pytest.raises(InputError, match=r"^where must be float \(a finite number\), got "):
            convert(bad, float, "where")
    assert convert("none", float | None, "where") is None and convert(2**70, float, "where") == 2.0**70


def test_unknown_keys_are_refused_with_the_nearest_known_key():
    where = Where("f.toml", "outer")
    with pytest.raises(InputError) as info:
        build(Outer, {"size": 1, "sise": 2}, where)
    assert str(info.value) == ("unknown key(s) ['sise'] in [outer] of f.toml; did you mean 'size'? "
                               "(known keys: size, when, vector, flag, inner)")
    with pytest.raises(InputError, match=r"unknown key\(s\) \['zzz'\] in \[outer.inner\] of f.toml \(known keys: "
                                         r"alpha, names\)$"):
        build(Outer, {"size": 1, "inner": {"zzz": 1}}, where)  # nothing close: the known keys only
    with pytest.raises(InputError, match=r"unknown section\(s\) \['outr'\] in f.toml; did you mean 'outer'\?"):
        build(dataclasses.make_dataclass("File", [("outer", Outer)], frozen=True), {"outr": {}}, Where("f.toml"),
              noun="section")


def test_set_overrides_are_typed_and_a_typo_gets_a_suggestion():
    where = Where("f.toml", "outer")
    value = build(Outer, {"size": 1}, where, overrides=parse_overrides(["size=7", "flag = true"]))
    assert value.size == 7 and value.flag is True
    with pytest.raises(InputError, match=r"^f.toml: --set size must be int \(a whole number\), got 'seven'$"):
        build(Outer, {"size": 1}, where, overrides={"size": "seven"})
    with pytest.raises(InputError, match=r"KEY=VALUE"):
        parse_overrides(["size"])
    with pytest.raises(InputError) as info:
        load_run_file(S1, {"duraton_days": "1"})
    message = str(info.value)
    assert message.startswith(f"unknown setting(s) ['duraton_days'] given by --set for [settings] of {S1}; "
                              "did you mean 'duration_days'?")
    with pytest.raises(InputError, match=r"unknown fault\(s\) \['outlier_fracton'\] given by --set for \[faults\] "
                                         r".*did you mean 'outlier_fraction'\?"):
        load_run_file(S1, {"faults.outlier_fracton": "0.1"})
    assert load_run_file(S1, {"duration_days": "1", "seed": "5"}).settings.duration_days == 1.0
    with pytest.raises(InputError, match="seed must be a non-negative integer"):
        load_run_file(S1, {"seed": "-1"})


def test_run_file_and_scene_file_typos_name_file_table_and_key(tmp_path):
    run = tmp_path / "run.toml"
    run.write_text(S1.read_text().replace("duration_days = 30.0", "duraton_days = 30.0"))
    with pytest.raises(InputError, match=rf"unknown setting\(s\) \['duraton_days'\] in \[settings\] of {run}; "
                                         r"did you mean 'duration_days'\?"):
        load_run_file(run)
    run.write_text(S1.read_text().replace("duration_days = 30.0", 'duration_days = "long"'))
    with pytest.raises(InputError, match=rf"^{run}: \[settings\] duration_days must be float \(a finite number\), "
                                         r"got 'long'$"):
        load_run_file(run)
    scene = tmp_path / "scene.toml"
    scene.write_text((ROOT / "samples" / "s1_render.toml").read_text().replace("sigma_px", "sigma_pix"))
    with pytest.raises(InputError, match=rf"unknown key\(s\) \['sigma_pix'\] in \[psf\] of {scene}; "
                                         r"did you mean 'sigma_px'\?"):
        load_scene(scene)


@pytest.mark.parametrize("old, new, message", [
    ("[navigation.corrections]", "[navigation.ukf]\nalpha = 2.0\n\n[navigation.corrections]",
     r"\[navigation.ukf\] UKFOptions.alpha must be in \(0, 1\], got 2.0"),
    ("[navigation.corrections]", "[navigation.ukf]\ngate_probability = 0.9\n\n[navigation.corrections]",
     r"unknown key\(s\) \['gate_probability'\] in \[navigation.ukf\]"),  # [navigation] gate_probability sets it
    ("[navigation.corrections]", "[navigation.particle]\nn_particle = 10\n\n[navigation.corrections]",
     r"unknown key\(s\) \['n_particle'\] in \[navigation.particle\] of .*; did you mean 'n_particles'\?"),
    ("[navigation.corrections]", "[navigation.particle.ukf]\nkappa = \"x\"\n\n[navigation.corrections]",
     r"\[navigation.particle.ukf\] kappa must be float"),
    ("[navigation.corrections]", "[navigation.batch]\nmax_iterations = 0\n\n[navigation.corrections]",
     r"\[navigation.batch\] BatchOptions.max_iterations must be >= 1"),
    ("[navigation.corrections]", "[navigation.federated]\nlocal_filter = \"pf\"\n\n[navigation.corrections]",
     r"\[navigation.federated\] FederatedSetup.local_filter must be one of ekf, ukf, sr-ukf, got 'pf'"),
    ('model = "white"', 'model = "brownian"', r"\[navigation.process_noise\] unknown process_noise model"),
    ("q_km2_s3 = 1.0e-19", "q_km2_s = 1.0e-19",
     r"unknown key\(s\) \['q_km2_s'\] in \[navigation.process_noise\] .*did you mean 'q_km2_s3'\?"),
])
def test_filter_options_fail_on_load_naming_file_table_and_key(tmp_path, old, new, message):
    path = tmp_path / "nav.toml"
    assert old in NAVIGATION
    path.write_text(NAVIGATION.replace(old, new, 1))
    with pytest.raises(InputError, match=message) as info:
        load_navigation(path)
    assert str(path) in str(info.value) and "\n" not in str(info.value)


def test_filter_options_are_typed_and_survive_a_json_round_trip(tmp_path):
    path = tmp_path / "nav.toml"
    path.write_text(NAVIGATION + "\n[navigation.ukf]\nalpha = 0.5\n\n[navigation.particle]\nn_particles = 300\n"
                    "\n[navigation.particle.ukf]\nkappa = 1.0\n\n[navigation.federated]\nfusion_interval_s = 60\n")
    nav = load_navigation(path)
    assert nav.ukf == UKFOptions(alpha=0.5) and nav.batch == BatchOptions()
    assert nav.particle == ParticleOptions(n_particles=300, ukf=UKFOptions(kappa=1.0))
    assert nav.federated == FederatedSetup(fusion_interval_s=60.0)
    # as opnav.studies.runner stores and reads back a simulation's navigation set-up
    data = dataclasses.asdict(nav)
    data["x0"], data["P0"] = np.array(data["x0"]), np.array(data["P0"])
    back = NavigationConfig(**data)
    assert (back.ukf, back.particle, back.batch, back.federated) == (nav.ukf, nav.particle, nav.batch, nav.federated)
    assert NavigationConfig(**{**data, "ukf": {}, "particle": {"n_particles": 150}}).particle.n_particles == 150
    with pytest.raises(InputError, match=r"\[navigation.ukf\]"):
        NavigationConfig(**{**data, "ukf": {"alfa": 0.5}})


@pytest.mark.parametrize("load, kind", [(load_scene, "scene file"), (load_navigation, "navigation file"),
                                        (load_run_file, "run file")])
def test_a_missing_file_names_its_kind(tmp_path, load, kind):
    path = tmp_path / "missing.toml"
    with pytest.raises(InputError, match=rf"^{kind} not found: {path}$"):
        load(path)
    path.write_text("x = [")
    with pytest.raises(InputError, match=rf"^{path}: not a readable TOML file"):
        read_toml(path, kind=kind)


def test_the_run_command_prints_one_line_with_the_suggestion(tmp_path, capsys):
    assert main(["run", str(S1), "--out", str(tmp_path / "x"), "--set", "duraton_days=1"]) == 2
    err = capsys.readouterr().err
    assert "did you mean 'duration_days'?" in err and err.count("\n") == 1
