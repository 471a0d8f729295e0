"""Star catalog: positions, space motion, parallax, aberration, cone search, file handling."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from astropy import units as u
from astropy.coordinates import SkyCoord
from astropy.time import Time
from scipy.spatial import cKDTree

from opnav.catalog import (
    SOURCE_GAIA,
    SOURCE_HIPPARCOS,
    StarCatalog,
    load_catalog,
    synthetic_catalog,
)
from opnav.constants import ARCSEC_RAD, AU_KM, C_KM_S, JULIAN_YEAR_S
from opnav.errors import CatalogError, InputError
from opnav.frames import angle_between, radec_to_unit
from opnav.epochs import parse_epoch

ZERO = np.zeros(3)
J1991_25 = (1991.25 - 2000.0) * JULIAN_YEAR_S
J2016 = 16.0 * JULIAN_YEAR_S


@pytest.fixture(scope="module")
def catalog() -> StarCatalog:
    return load_catalog()


def _row(catalog: StarCatalog, hip: int) -> int:
    (rows,) = np.nonzero(catalog.hip == hip)
    assert rows.size == 1
    return int(rows[0])


def _geometric(catalog, rows, t_tdb_s, r_observer=ZERO, **switches):
    return catalog.apparent_directions(
        np.atleast_1d(rows), t_tdb_s=t_tdb_s, r_observer_ssb_km=r_observer, v_observer_ssb_km_s=ZERO,
        aberration=False, **switches,
    )


@pytest.mark.parametrize(
    "hip, ra_hms, dec_dms",
    [
        # SIMBAD ICRS J2000 coordinates (from van Leeuwen 2007) of Vega and Sirius.
        (91262, "18h36m56.33635s", "+38d47m01.2802s"),
        (32349, "06h45m08.91728s", "-16d42m58.0171s"),
    ],
)
def test_known_star_reproduces_published_icrs_position(catalog, hip, ra_hms, dec_dms):
    published = SkyCoord(ra_hms, dec_dms, frame="icrs")
    expected = radec_to_unit(published.ra.rad, published.dec.rad)
    at_j2000 = _geometric(catalog, _row(catalog, hip), 0.0, parallax=False)[0]
    assert angle_between(at_j2000, expected) / ARCSEC_RAD < 0.005


def test_barnards_star_moves_its_proper_motion_in_25_years(catalog):
    row = _row(catalog, 87937)
    mu_arcsec_yr = np.hypot(catalog.pm_ra_cosdec_rad_yr[row], catalog.pm_dec_rad_yr[row]) / ARCSEC_RAD
    assert mu_arcsec_yr == pytest.approx(10.36, abs=0.02)  # published 10.3"/yr
    t0 = catalog.epoch_tdb_s[row]
    start, end = _geometric(catalog, [row, row], t0, parallax=False)[0], _geometric(
        catalog, row, t0 + 25.0 * JULIAN_YEAR_S, parallax=False
    )[0]
    moved_arcsec = angle_between(start, end) / ARCSEC_RAD
    # Straight-line motion seen from the SSB: atan(mu t) differs from mu t by < 1e-3".
    assert moved_arcsec == pytest.approx(25.0 * mu_arcsec_yr, abs=1e-3)
    assert end[2] > start[2]  # Barnard's star moves north


@pytest.mark.parametrize("hip", [87937, 91262, 30438])
def test_space_motion_matches_astropy(catalog, hip):
    row = _row(catalog, hip)
    coord = SkyCoord(
        ra=catalog.ra_rad[row] * u.rad, dec=catalog.dec_rad[row] * u.rad,
        distance=(AU_KM / catalog.parallax_rad[row]) * u.km,
        pm_ra_cosdec=catalog.pm_ra_cosdec_rad_yr[row] * u.rad / u.yr, pm_dec=catalog.pm_dec_rad_yr[row] * u.rad / u.yr,
        radial_velocity=catalog.rv_km_s[row] * u.km / u.s, obstime=Time(1991.25, format="jyear", scale="tdb"),
    )
    moved = coord.apply_space_motion(new_obstime=Time(2016.0, format="jyear", scale="tdb"))
    expected = radec_to_unit(moved.ra.rad, moved.dec.rad)
    ours = _geometric(catalog, row, J2016, parallax=False)[0]
    # ERFA's starpm adds a light-time term (v_r/c of the displacement): < 1e-3" here.
    assert angle_between(ours, expected) / ARCSEC_RAD < 1e-3


def test_radial_velocity_changes_proper_motion_as_the_star_approaches(catalog):
    row = _row(catalog, 91262)  # Vega, approaching at 20.6 km/s
    velocity = catalog.space_velocity_km_s([row])[0]
    u0 = catalog.unit_vectors()[row]
    distance_km = AU_KM / catalog.parallax_rad[row]
    v_radial = velocity @ u0
    v_tangential = np.linalg.norm(velocity - v_radial * u0)
    dt_s = 2.0e4 * JULIAN_YEAR_S
    expected_rad = np.arctan2(v_tangential * dt_s, distance_km + v_radial * dt_s)
    moved = _geometric(catalog, row, catalog.epoch_tdb_s[row] + dt_s, parallax=False)[0]
    assert angle_between(u0, moved) == pytest.approx(expected_rad, rel=1e-9)
    frozen = _geometric(catalog, row, catalog.epoch_tdb_s[row] + dt_s, parallax=False, proper_motion=False)[0]
    assert angle_between(u0, frozen) < 1e-15
    assert expected_rad > np.arctan(v_tangential * dt_s / distance_km)  # approaching: grows faster


def test_alpha_centauri_parallax_from_one_au(catalog):
    row = _row(catalog, 71683)
    u0 = catalog.unit_vectors()[row]
    across = np.cross(u0, [0.0, 0.0, 1.0])
    across *= AU_KM / np.linalg.norm(across)
    t = catalog.epoch_tdb_s[row]
    at_ssb = _geometric(catalog, row, t)[0]
    shift_arcsec = angle_between(at_ssb, _geometric(catalog, row, t, r_observer=across)[0]) / ARCSEC_RAD
    assert shift_arcsec == pytest.approx(np.arctan(catalog.parallax_rad[row]) / ARCSEC_RAD, rel=1e-6)
    assert shift_arcsec == pytest.approx(0.755, abs=0.01)  # published 0.747-0.755"
    along = angle_between(at_ssb, _geometric(catalog, row, t, r_observer=AU_KM * u0)[0])
    assert along / ARCSEC_RAD < 1e-6
    no_parallax = _geometric(catalog, row, t, r_observer=across, parallax=False)[0]
    assert angle_between(at_ssb, no_parallax) / ARCSEC_RAD < 1e-9


def test_aberration_for_30_km_s_at_90_degrees():
    star = synthetic_catalog(1, rng=np.random.default_rng(3))
    u0 = star.unit_vectors()[0]
    velocity = np.cross(u0, [0.0, 0.0, 1.0])
    velocity *= 30.0 / np.linalg.norm(velocity)
    apparent = star.apparent_directions(t_tdb_s=0.0, r_observer_ssb_km=ZERO, v_observer_ssb_km_s=velocity)[0]
    beta = 30.0 / C_KM_S
    shift_arcsec = angle_between(u0, apparent) / ARCSEC_RAD
    assert shift_arcsec == pytest.approx(np.arctan(beta / np.sqrt(1 - beta**2)) / ARCSEC_RAD, abs=1e-6)
    assert shift_arcsec == pytest.approx(20.6, abs=0.1)
    assert apparent @ velocity > 0.0  # displaced towards the direction of motion


@pytest.mark.parametrize("radius_deg, vmag_limit", [(1.0, None), (5.0, None), (12.0, 7.0)])
def test_cone_search_equals_brute_force(catalog, radius_deg, vmag_limit):
    rng = np.random.default_rng(11)
    vectors = catalog.unit_vectors()
    radius = np.radians(radius_deg)
    for center in rng.normal(size=(5, 3)):
        found = catalog.cone(center, radius, vmag_limit=vmag_limit)
        angle = angle_between(vectors, center / np.linalg.norm(center))
        inside = angle <= radius
        if vmag_limit is not None:
            inside &= catalog.vmag <= vmag_limit
        assert set(found.tolist()) == set(np.flatnonzero(inside).tolist())
        assert found.size == np.unique(found).size
        assert np.all(np.diff(catalog.vmag[found]) >= 0.0)


def test_no_duplicate_stars(catalog):
    at_j2016 = _geometric(catalog, np.arange(len(catalog)), J2016, parallax=False)
    pairs = cKDTree(at_j2016).query_pairs(2.0 * np.sin(0.5 * ARCSEC_RAD), output_type="ndarray")
    delta_v = np.abs(catalog.vmag[pairs[:, 0]] - catalog.vmag[pairs[:, 1]]) if len(pairs) else np.zeros(0)
    assert np.all(delta_v >= 0.5)
    assert np.unique(catalog.star_id).size == len(catalog)


def test_catalog_content_is_sane(catalog):
    bright = int(np.sum(catalog.vmag < 6.0))
    assert 4500 < bright < 5800  # about 5000 stars are brighter than V = 6
    hipparcos = catalog.source == SOURCE_HIPPARCOS
    assert hipparcos.sum() == 117_955
    assert np.all(catalog.hip[hipparcos] > 0) and np.all(catalog.gaia_id[hipparcos] == 0)
    gaia = catalog.source == SOURCE_GAIA
    assert np.all(catalog.gaia_id[gaia] > 2**35) and np.all(catalog.hip[gaia] == 0)
    assert not np.any(catalog.has_pm[gaia]) and np.all(catalog.pm_dec_rad_yr[gaia] == 0.0)
    assert np.allclose(catalog.epoch_tdb_s[hipparcos], J1991_25)
    assert np.allclose(catalog.epoch_tdb_s[gaia], J2016)
    assert catalog.vmag[_row(catalog, 91262)] == pytest.approx(0.03, abs=0.1)  # Vega V = 0.03


def test_gaia_star_without_motion_stays_put(catalog):
    row = int(np.flatnonzero(catalog.source == SOURCE_GAIA)[0])
    later = _geometric(catalog, row, catalog.epoch_tdb_s[row] + 50 * JULIAN_YEAR_S, r_observer=np.full(3, AU_KM))
    assert angle_between(later[0], catalog.unit_vectors()[row]) < 1e-15


@pytest.mark.parametrize("hip, rv_km_s", [(91262, -20.6), (30438, 20.3)])
def test_star_velocity_has_inserted_radial_velocity(catalog, hip, rv_km_s):
    row = _row(catalog, hip)
    velocity = catalog.space_velocity_km_s(np.array([row]))[0]
    u0 = catalog.unit_vectors()[row]
    assert velocity @ u0 == pytest.approx(rv_km_s, abs=1e-9)
    # Tangential speed 4.74047 km/s per (arcsec/yr / arcsec of parallax).
    mu = np.hypot(catalog.pm_ra_cosdec_rad_yr[row], catalog.pm_dec_rad_yr[row])
    tangential = np.linalg.norm(velocity - (velocity @ u0) * u0)
    assert tangential == pytest.approx(4.740470 * mu / catalog.parallax_rad[row], rel=1e-6)


def test_space_velocity_needs_parallax(catalog):
    with pytest.raises(CatalogError, match="parallax"):
        catalog.space_velocity_km_s(np.flatnonzero(catalog.source == SOURCE_GAIA)[:3])


def test_bad_observer_state_is_an_input_error(catalog):
    with pytest.raises(InputError, match="r_observer_ssb_km"):
        catalog.apparent_directions([0], t_tdb_s=0.0, r_observer_ssb_km=[np.nan, 0, 0], v_observer_ssb_km_s=ZERO)
    with pytest.raises(InputError, match="v_observer_ssb_km_s"):
        catalog.apparent_directions([0], t_tdb_s=0.0, r_observer_ssb_km=ZERO, v_observer_ssb_km_s=[1.0, 2.0])
    with pytest.raises(InputError, match="t_tdb_s"):
        catalog.apparent_directions([0], t_tdb_s=np.inf, r_observer_ssb_km=ZERO, v_observer_ssb_km_s=ZERO)
    with pytest.raises(InputError, match="radius_rad"):
        catalog.cone([1.0, 0.0, 0.0], 0.0)
    with pytest.raises(InputError, match="center_icrf"):
        catalog.cone([0.0, 0.0, 0.0], 0.1)


def test_missing_file_is_a_catalog_error(tmp_path, monkeypatch):
    with pytest.raises(CatalogError, match="not found"):
        load_catalog(tmp_path / "nowhere.npz")
    monkeypatch.setenv("OPNAV_CATALOG", str(tmp_path / "env.npz"))
    with pytest.raises(CatalogError, match="env.npz"):
        load_catalog()


def test_corrupt_file_is_a_catalog_error(tmp_path):
    garbage = tmp_path / "garbage.npz"
    garbage.write_bytes(b"not a zip file at all")
    with pytest.raises(CatalogError, match="not an opnav catalog"):
        load_catalog(garbage)
    random_bytes = tmp_path / "random.npz"
    random_bytes.write_bytes(np.random.default_rng(0).bytes(4096))
    with pytest.raises(CatalogError, match="not an opnav catalog") as info:
        load_catalog(random_bytes)
    assert "pickle" not in str(info.value)
    truncated = tmp_path / "truncated.npz"
    truncated.write_bytes(b"PK\x03\x04" + b"\0" * 64)
    with pytest.raises(CatalogError, match="unreadable"):
        load_catalog(truncated)
    incomplete = tmp_path / "incomplete.npz"
    np.savez(incomplete, format_version=np.array(1), hip=np.arange(3))
    with pytest.raises(CatalogError, match="lacks column"):
        load_catalog(incomplete)


def test_saved_catalog_round_trips_through_env_variable(tmp_path, monkeypatch):
    stars = synthetic_catalog(50, rng=np.random.default_rng(5))
    path = tmp_path / "small.npz"
    np.savez(path, format_version=np.array(1), **{name: getattr(stars, name) for name in stars.__dataclass_fields__})
    monkeypatch.setenv("OPNAV_CATALOG", str(path))
    loaded = load_catalog()
    assert len(loaded) == 50 and np.array_equal(loaded.star_id, stars.star_id)
    assert np.array_equal(loaded.unit_vectors(), stars.unit_vectors())


def test_catalog_arrays_are_read_only_and_subset_consistent(catalog):
    with pytest.raises(ValueError):
        catalog.vmag[0] = 0.0
    rows = np.array([5, 1, 7])
    part = catalog.subset(rows)
    assert len(part) == 3
    assert np.array_equal(part.star_id, catalog.star_id[rows])
    assert np.array_equal(part.unit_vectors(), catalog.unit_vectors()[rows])


def test_synthetic_catalog_is_uniform_and_validated():
    n = 20_000
    stars = synthetic_catalog(n, rng=np.random.default_rng(2), vmag_range=(3.0, 6.0))
    # Mean of uniform unit vectors: each component has variance 1/3, so 5 sigma = 5/sqrt(3n).
    assert np.all(np.abs(stars.unit_vectors().mean(axis=0)) < 5.0 / np.sqrt(3.0 * n))
    assert stars.vmag.min() >= 3.0 and stars.vmag.max() <= 6.0
    assert np.unique(stars.star_id).size == n
    with pytest.raises(InputError, match="rng"):
        synthetic_catalog(3, rng=1)
    with pytest.raises(InputError, match="dec_rad"):
        StarCatalog(**{**{k: getattr(stars, k) for k in stars.__dataclass_fields__}, "dec_rad": np.zeros(2)})


def test_epoch_constants_match_astropy():
    assert parse_epoch("1991-04-02T13:30:00", scale="tdb") == pytest.approx(J1991_25, abs=1.0)
    assert Time(2016.0, format="jyear", scale="tdb").jd == pytest.approx(2451545.0 + J2016 / 86400.0)


def test_synthetic_catalog_cap_is_uniform_in_solid_angle():
    rng = np.random.default_rng(8)
    centre = np.array([0.3, -0.2, 0.93])
    centre /= np.linalg.norm(centre)
    radius = np.radians(2.0)
    cat = synthetic_catalog(4000, rng=rng, centre_icrf=centre, radius_rad=radius)
    offset = np.arccos(np.clip(cat.unit_vectors() @ centre, -1.0, 1.0))
    assert offset.max() <= radius * (1 + 1e-12)
    # uniform in solid angle: the fraction inside half the radius is (1 - cos(r/2)) / (1 - cos r) ~ 1/4
    expected = (1 - np.cos(radius / 2)) / (1 - np.cos(radius))
    fraction = np.mean(offset < radius / 2)
    assert abs(fraction - expected) < 4 * np.sqrt(expected * (1 - expected) / 4000)
    with pytest.raises(InputError, match="both"):
        synthetic_catalog(10, rng=rng, centre_icrf=centre)


def test_saved_catalog_loads_back_equal(tmp_path):
    from opnav.catalog import save_catalog

    catalog = synthetic_catalog(40, rng=np.random.default_rng(3), vmag_range=(3.0, 9.0))
    loaded = load_catalog(save_catalog(catalog, tmp_path / "mine.npz"))
    for name in ("hip", "gaia_id", "ra_rad", "dec_rad", "epoch_tdb_s", "pm_ra_cosdec_rad_yr", "pm_dec_rad_yr",
                 "parallax_rad", "rv_km_s", "vmag", "source", "has_pm"):
        np.testing.assert_array_equal(getattr(loaded, name), getattr(catalog, name))


def test_default_catalog_is_package_data(monkeypatch):
    import opnav
    from opnav.catalog import default_catalog_path

    path = default_catalog_path()
    assert path.name == "stars.npz" and path.is_file()
    assert path.parent == Path(opnav.__file__).resolve().parent / "data"
    assert (path.parent / "stars.README.md").is_file()  # its source and licence note travels with it
    monkeypatch.setenv("OPNAV_CATALOG", "")  # empty: the default, not the current folder
    assert load_catalog() is load_catalog(path)


def test_stars_selected_by_rows_mask_or_negative_rows_are_the_same(catalog):
    # apparent_directions and space_velocity_km_s take integer rows as given (opnav solve asks for a few
    # stars at a time) and a mask through the catalog's rows: the same stars either way
    rows = np.array([5, 17, 3, len(catalog) - 1])
    mask = np.zeros(len(catalog), bool)
    mask[rows] = True
    state = dict(t_tdb_s=4.6e8, r_observer_ssb_km=np.array([1.4e8, -3e7, 2e6]), v_observer_ssb_km_s=ZERO)
    by_rows = catalog.apparent_directions(np.sort(rows), **state)
    np.testing.assert_array_equal(catalog.apparent_directions(mask, **state), by_rows)
    np.testing.assert_array_equal(catalog.apparent_directions(np.sort(rows) - len(catalog), **state), by_rows)
    np.testing.assert_array_equal(catalog.apparent_directions(**state)[np.sort(rows)], by_rows)


# --- the unpacked copy (memory-mapped columns instead of unpacking the .npz each process) ------------


def _copy_of_default(tmp_path, monkeypatch) -> Path:
    """The default catalog copied to ``tmp_path`` (its own unpacked copy), the cache in ``tmp_path/cache``."""
    import shutil

    from opnav.catalog import _load_cached, default_catalog_path

    source = tmp_path / "stars.npz"
    shutil.copyfile(default_catalog_path(), source)
    monkeypatch.setenv("OPNAV_CACHE", str(tmp_path / "cache"))
    _load_cached.cache_clear()
    return source


def _fresh(path: Path) -> StarCatalog:
    from opnav.catalog import _load_cached

    _load_cached.cache_clear()
    return load_catalog(path)


def test_unpacked_copy_holds_the_npz_catalog_with_its_unit_vectors(tmp_path, monkeypatch):
    from opnav.catalog import _read_npz

    source = _copy_of_default(tmp_path, monkeypatch)
    packed = _read_npz(source)
    first = _fresh(source)  # reads the .npz, writes the copy
    (copy,) = (tmp_path / "cache").glob("catalog-*")
    second = _fresh(source)  # from the copy
    assert isinstance(second.__dict__.get("_unit_vectors"), np.ndarray)  # came with the copy, not computed
    for name in StarCatalog.__dataclass_fields__:
        for loaded in (first, second):
            assert getattr(loaded, name).dtype == getattr(packed, name).dtype
            assert np.array_equal(getattr(loaded, name), getattr(packed, name)), name
    assert np.array_equal(second.unit_vectors(), radec_to_unit(packed.ra_rad, packed.dec_rad))
    with pytest.raises(ValueError):
        second.ra_rad[0] = 0.0
    with pytest.raises(ValueError):
        second.unit_vectors()[0, 0] = 0.0
    assert np.array_equal(second.cone([1.0, 0.0, 0.0], 0.02), packed.cone([1.0, 0.0, 0.0], 0.02))
    # a damaged copy (cut short) is read from the .npz again and written anew
    column = copy / "ra_rad.npy"
    column.write_bytes(column.read_bytes()[:1000])
    assert np.array_equal(_fresh(source).ra_rad, packed.ra_rad)
    assert column.stat().st_size == packed.ra_rad.nbytes + 128
    # a copy that lost its marker is not read
    (copy / "complete.json").unlink()
    assert np.array_equal(_fresh(source).dec_rad, packed.dec_rad)
    assert (copy / "complete.json").is_file()


def test_a_changed_catalog_file_gets_a_new_copy_and_the_old_one_goes(tmp_path, monkeypatch):
    import os

    source = _copy_of_default(tmp_path, monkeypatch)
    _fresh(source)
    (old,) = (tmp_path / "cache").glob("catalog-*")
    stat = source.stat()
    os.utime(source, ns=(stat.st_atime_ns, stat.st_mtime_ns + 1_000_000_000))
    _fresh(source)
    (new,) = (tmp_path / "cache").glob("catalog-*")
    assert new != old and not old.exists()
    # a copy of a catalog file that is gone (a removed checkout) goes when another copy is written
    other = tmp_path / "other.npz"
    other.write_bytes(source.read_bytes())
    _fresh(other)
    assert len(list((tmp_path / "cache").glob("catalog-*"))) == 2
    other.unlink()
    os.utime(source, ns=(stat.st_atime_ns, stat.st_mtime_ns + 2_000_000_000))
    _fresh(source)
    assert len(list((tmp_path / "cache").glob("catalog-*"))) == 1


def test_small_catalogs_and_unwritable_caches_are_read_from_their_file(tmp_path, monkeypatch):
    from opnav.catalog import save_catalog

    monkeypatch.setenv("OPNAV_CACHE", str(tmp_path / "cache"))
    stars = synthetic_catalog(500, rng=np.random.default_rng(3))
    loaded = _fresh(save_catalog(stars, tmp_path / "small.npz"))
    assert np.array_equal(loaded.unit_vectors(), stars.unit_vectors())
    assert not (tmp_path / "cache").exists()
    blocker = tmp_path / "file"
    blocker.write_text("a file where the cache folder would be")
    monkeypatch.setenv("OPNAV_CACHE", str(blocker / "cache"))
    source = tmp_path / "big.npz"
    source.write_bytes(Path(_copy_of_default(tmp_path, monkeypatch)).read_bytes())
    monkeypatch.setenv("OPNAV_CACHE", str(blocker / "cache"))
    assert len(_fresh(source)) == len(load_catalog())
