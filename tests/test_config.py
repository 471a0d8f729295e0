"""opnav.config, the one loader: typed tables, unknown keys with a suggestion, --set overrides,
typed filter options that fail on load, missing files named by their kind, and the one rule of
every file for text, case and dates (issue 40)."""

from __future__ import annotations

import dataclasses
import datetime
from dataclasses import dataclass, field
from pathlib import Path

import tomllib

import numpy as np
import pytest

from opnav.cli import main
from opnav.config import CalendarText, Where, build, check_zone, convert, parse_overrides, read_toml
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
    with pytest.raises(InputError, match=r"\[outer\] vector must be an array of 3 finite numbers \(0 or of magnitude 1e-150 to 1e\+150\), got \[1, 2\]"):
        build(Outer, {"size": 1, "vector": [1, 2]}, where)


def test_toml_values_in_files_and_text_only_as_set_gives_it():
    where = Where("f.toml", "outer")
    # TOML values only, in every file: text is not a number, a boolean or an array, and the message says so
    with pytest.raises(InputError, match=r"^f.toml: \[outer\] flag must be true or false \(written without "
                                         r"quotes\), got 'false'$"):
        build(Outer, {"size": 1, "flag": "false"}, where)
    with pytest.raises(InputError, match=r"\[outer\] size must be int \(a whole number\), got 1.5"):
        build(Outer, {"size": 1.5}, where)
    for table, message in (({"size": "4"}, r"size must be int \(a whole number\) \(written without quotes\), got '4'"),
                           ({"size": 1, "vector": "1, 2, 3"}, r"vector must be an array of 3 finite numbers "
                                                              r"\(0 or of magnitude 1e-150 to 1e\+150\) "
                                                              r"\(written as a TOML array, \[a, b, ...\]\)"),
                           ({"size": 1, "when": "none"}, None),
                           ({"size": 1, "inner": {"names": "a,b"}}, r"\[outer.inner\] names must be an array")):
        if message is None:  # a date field takes any text; the loader parses it
            assert build(Outer, table, where).when == "none"
            continue
        for text in (False, True):  # build(text=True), as the scene and run loaders once asked, reads no text
            with pytest.raises(InputError, match=message):
                build(Outer, table, where, text=text)
    # a float without fraction for an integer, and an integer for a float, in a file too
    assert build(Outer, {"size": 4.0, "vector": [1, 2, 3]}, where) == Outer(4, vector=(1.0, 2.0, 3.0))
    # text only as --set gives it
    value = build(Outer, {"size": 1}, where, overrides={"size": "4", "flag": "yes", "vector": "1, 2, 3"})
    assert value == Outer(4, None, (1.0, 2.0, 3.0), True)
    for bad in ("nan", "1e999", "big", True):
        with pytest.raises(InputError, match=r"^where must be float \(a finite number: 0 or of magnitude 1e-150 to 1e\+150\), got "):
            convert(bad, float, "where")
    assert convert("none", float | None, "where") is None and convert(2**70, float, "where") == 2.0**70


@dataclass(frozen=True)
class Named:
    law: str = field(default="inertial", metadata={"choices": ("target", "earth", "inertial")})
    bodies: tuple[str, ...] = field(default=(), metadata={"choices": lambda: ("phobos", "deimos", "sr-ukf")})
    label: str = "Free Text"  # not an enumeration: kept as written
    kind: str | None = None


def test_enumerated_names_take_any_case_and_are_stored_as_listed():
    where = Where("f.toml", "t")
    value = build(Named, {"law": "Target", "bodies": ["PHOBOS", " Deimos", "SR-UKF"], "label": "ICRF"}, where)
    assert value == Named("target", ("phobos", "deimos", "sr-ukf"), "ICRF")
    with pytest.raises(InputError, match=r"^f.toml: \[t\] law must be one of target, earth, inertial, got 'traget' "
                                         r"\(did you mean 'target'\?\)$"):
        build(Named, {"law": "traget"}, where)
    with pytest.raises(InputError, match=r"^f.toml: \[t\] bodies must be names from phobos, deimos, sr-ukf, "
                                         r"got 'nosuch'$"):
        build(Named, {"bodies": ["phobos", "nosuch"]}, where)
    # a class the loader does not own names its enumerations through build(choices=...)
    assert build(Named, {"kind": "AIRY"}, where, choices={Named: {"kind": ("gaussian", "airy")}}).kind == "airy"
    with pytest.raises(InputError, match=r"kind must be one of gaussian, airy, got 'moffat'"):
        build(Named, {"kind": "moffat"}, where, choices={Named: {"kind": ("gaussian", "airy")}})
    # --set values follow the same rule
    assert build(Named, {}, where, overrides={"law": "EARTH", "bodies": "Phobos, deimos"}) == Named(
        "earth", ("phobos", "deimos"))


def test_toml_date_times_with_a_zone_become_utc_text_as_quoted_ones_are():
    where = "f.toml: [epochs] start"
    zulu = datetime.datetime(2014, 7, 15, tzinfo=datetime.timezone.utc)
    plus2 = datetime.datetime(2014, 7, 15, 2, 0, 0, 500000, tzinfo=datetime.timezone(datetime.timedelta(hours=2)))
    assert convert(zulu, CalendarText, where, text=False) == "2014-07-15T00:00:00Z"
    assert convert(plus2, CalendarText, where, text=False) == "2014-07-15T00:00:00.500000Z"
    assert convert(datetime.datetime(2014, 7, 15), CalendarText, where, text=False) == "2014-07-15 00:00:00"
    # as the file is parsed: the unquoted date-time with an offset is the quoted "...Z"
    path_of = {}
    for name, text in (("quoted", 'when = "2014-07-15T00:00:00Z"'), ("offset", "when = 2014-07-15T02:00:00+02:00"),
                       ("zulu", "when = 2014-07-15T00:00:00Z")):
        path_of[name] = build(Outer, {"size": 1, **tomllib.loads(text)}, Where(name)).when
    assert len(set(path_of.values())) == 1
    check_zone("2014-07-15T00:00:00Z", "UTC", where)
    check_zone("2014-07-15T00:00:00", "tt", where)
    with pytest.raises(InputError, match=r"^f.toml: \[epochs\] start '2014-07-15T00:00:00Z' is a UTC date .* "
                                         r"its scale is 'tt'"):
        check_zone("2014-07-15T00:00:00Z", "tt", where)


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
    with pytest.raises(InputError, match=rf"^{run}: \[settings\] duration_days must be float \(a finite number: 0 or of magnitude 1e-150 to 1e\+150\), "
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
     r"\[navigation.ukf\] gate_probability cannot be set here: the gate of every filter is \[navigation\] "
     r"gate_probability$"),
    ("[navigation.corrections]", "[navigation.particle]\nmcmc_move = false\n\n[navigation.corrections]",
     r"\[navigation.particle\] mcmc_move cannot be set here: the MCMC move follows \[navigation\] filter"),
    ("[navigation.corrections]", "[navigation.particle]\nn_particle = 10\n\n[navigation.corrections]",
     r"unknown key\(s\) \['n_particle'\] in \[navigation.particle\] of .*; did you mean 'n_particles'\?"),
    ("[navigation.corrections]", "[navigation.particle.ukf]\nkappa = \"x\"\n\n[navigation.corrections]",
     r"\[navigation.particle.ukf\] kappa must be float"),
    ("[navigation.corrections]", "[navigation.batch]\nmax_iterations = 0\n\n[navigation.corrections]",
     r"\[navigation.batch\] BatchOptions.max_iterations must be >= 1"),
    ("[navigation.corrections]", "[navigation.federated]\nlocal_filter = \"pf\"\n\n[navigation.corrections]",
     r"\[navigation.federated\] local_filter must be one of ekf, ukf, sr-ukf, got 'pf'"),
    ('model = "white"', 'model = "brownian"',
     r"\[navigation.process_noise\] model must be one of white, snc, none, got 'brownian'"),
    # a density the model does not use is refused, named (issue 40)
    ('model = "white"', 'model = "none"',
     r"\[navigation.process_noise\] q_km2_s3 is not used by process_noise model 'none', which uses no density"),
    ("q_km2_s3 = 1.0e-19", "q_km2_s3 = 1.0e-19\nq_ric_km2_s3 = [1e-14, 1e-14, 1e-14]",
     r"\[navigation.process_noise\] q_ric_km2_s3 is not used by process_noise model 'white', which uses q_km2_s3 only"),
    ('model = "white"\nq_km2_s3 = 1.0e-19', 'model = "snc"\nq_km2_s3 = 1.0e-19\nq_ric_km2_s3 = [1e-14, 1e-14, 1e-14]',
     r"q_km2_s3 is not used by process_noise model 'snc', which uses q_ric_km2_s3 only"),
    # names checked on load, not when the filter is built
    ('dynamics = "cruise"\nposition', 'dynamics = "crusie"\nposition',
     r"\[navigation\] dynamics must be one of cruise, capture1, capture2, geo, approach, got 'crusie' "
     r"\(did you mean 'cruise'\?\)"),
    ('filter = "ekf"', 'filter = "ekf"\nephemeris_targets = ["phobos", "nosuch"]',
     r"\[navigation\] ephemeris_targets must be names from .*phobos.*, got 'nosuch'"),
    ('filter = "ekf"', 'filter = "ekf"\nephemeris_targets = ["phobos", "Phobos"]',
     r"\[navigation\] ephemeris_targets lists 'phobos' more than once; give each name once"),
    ('filter = "ekf"', 'filter = "ekf"\nseed = "3"', r"\[navigation\] seed must be int .*\(written without quotes\)"),
    ('epoch = "2014-07-15T00:00:00"\nepoch_scale = "utc"', 'epoch = 2014-07-15T00:00:00Z\nepoch_scale = "tt"',
     r"'2014-07-15T00:00:00Z' is a UTC date .* its scale is 'tt'"),
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


def test_navigation_names_take_any_case_and_dates_any_zone(tmp_path):
    path = tmp_path / "nav.toml"
    reference = load_navigation(ROOT / "opnav" / "data" / "demo.toml")
    text = (NAVIGATION.replace('filter = "ekf"', 'filter = "EKF"\nephemeris_targets = ["PHOBOS", "Deimos"]\n'
                                                 'propagation = "Fast"\nephemeris_error = "WHITE"')
            .replace('dynamics = "cruise"\nposition', 'dynamics = "Cruise"\nposition')
            .replace('epoch = "2014-07-15T00:00:00"\nepoch_scale = "utc"', 'epoch = 2014-07-15T01:00:00+01:00\n'
                                                                        'epoch_scale = "UTC"')
            .replace('model = "white"', 'model = "White"')
            + '\n[navigation.federated]\nlocal_filter = "SR-UKF"\nmode = "No-Reset"\n')
    path.write_text(text)
    nav = load_navigation(path)
    assert (nav.filter, nav.dynamics, nav.exact, nav.ephemeris_error) == ("ekf", "cruise", False, "white")
    assert nav.ephemeris_targets == ("phobos", "deimos") and nav.process_noise == {"model": "white", "q_km2_s3": 1e-19}
    assert nav.t0_tdb_s == reference.t0_tdb_s
    assert nav.federated == FederatedSetup(local_filter="sr-ukf", mode="no-reset")


def test_run_files_hold_toml_values_only_and_set_text_still_works(tmp_path):
    run = tmp_path / "run.toml"
    run.write_text(S1.read_text().replace("duration_days = 30.0", 'duration_days = "30"'))
    with pytest.raises(InputError, match=rf"^{run}: \[settings\] duration_days must be float \(a finite number: 0 or of magnitude 1e-150 to 1e\+150\) "
                                         r"\(written without quotes\), got '30'$"):
        load_run_file(run)
    assert load_run_file(S1, {"duration_days": "2", "targets": "phobos"}).settings.duration_days == 2.0


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
    with pytest.raises(InputError, match=rf"^{kind} not found: {path}($| )"):
        load(path)
    path.write_text("x = [")
    with pytest.raises(InputError, match=rf"^{path}: not a readable TOML file"):
        read_toml(path, kind=kind)


def test_the_run_command_prints_one_line_with_the_suggestion(tmp_path, capsys):
    assert main(["run", str(S1), "--out", str(tmp_path / "x"), "--set", "duraton_days=1"]) == 2
    err = capsys.readouterr().err
    assert "did you mean 'duration_days'?" in err and err.count("\n") == 1


@pytest.mark.parametrize("value", ["1e300", "-1e200", "1e-300", "-2e-160"])
def test_a_float_whose_square_would_overflow_or_underflow_is_refused(value):
    """noise_arcsec = 1e300 overflowed in the simulation and 1e-300 made every covariance singular: a
    float setting is 0 or of magnitude 1e-150 to 1e150, so squares and products stay computable."""
    with pytest.raises(InputError, match=r"^where must be float \(a finite number: 0 or of magnitude 1e-150"):
        convert(value, float, "where", text=True)
    assert convert("0", float, "where", text=True) == 0.0
    assert convert("1e-149", float, "where", text=True) == 1e-149


def test_an_array_of_names_that_repeats_a_name_is_refused(tmp_path):
    """A target listed twice was rendered twice (twice its flux): every enumerated array takes each name once."""
    from opnav.sim.scene import demo_scene_path, load_scene

    text = demo_scene_path().read_text()
    assert 'names = ["phobos", "deimos", "mars"]' in text
    scene = tmp_path / "scene.toml"
    scene.write_text(text.replace('names = ["phobos", "deimos", "mars"]', 'names = ["phobos", "deimos", "mars", "Phobos"]'))
    with pytest.raises(InputError, match=r"\[targets\] names lists 'phobos' more than once; give each name once"):
        load_scene(scene)
