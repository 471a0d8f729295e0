"""Fitted ephemeris segments kept on disk (opnav.ephemeris.segment_store) and read back by a later cache."""

import numpy as np
import pytest

from opnav.ephemeris import Ephemeris
from opnav.ephemeris.cache import EphemerisCache
from opnav.ephemeris.segment_store import CHECK_POSITION_KM, SegmentStore, _checksum, pair_key, source_identity
from opnav.epochs import parse_epoch

T0 = parse_epoch("2014-07-01T00:00:00", scale="tdb")
PAIRS = [("phobos", "mars"), ("deimos", "ssb"), ("mars", "sun"), ("earth", "sun")]
EPOCHS = T0 + np.random.default_rng(3).uniform(0.0, 2 * 86_400.0, 300)


def _counting_source():
    """A default Ephemeris whose state calls are counted (by the number of epochs asked)."""
    source = Ephemeris()
    exact, asked = source.state, []

    def state(body, t, *, center="ssb"):
        asked.append(np.size(t))
        return exact(body, t, center=center)

    source.state = state
    return source, asked


def _states(cache):
    """Every pair's states at EPOCHS by the array path, the scalar path and the dense tables."""
    out = []
    for body, center in PAIRS:
        out.append(np.hstack(cache.state(body, EPOCHS, center=center)))
        out.append(np.array([np.hstack(cache.state(body, float(t), center=center)) for t in EPOCHS[:20]]))
        out.append(cache.table(body, center, T0, T0 + 86_400.0).coefficients)
    return out


def test_a_later_cache_reads_the_stored_segments_and_answers_to_the_bit(tmp_path):
    store = SegmentStore(tmp_path)
    first = EphemerisCache(Ephemeris(), store=store)
    fitted = _states(first)
    first.save()
    assert len(list(tmp_path.glob("*.npz"))) == len(PAIRS)
    source, asked = _counting_source()
    later = EphemerisCache(source, store=store)
    assert all(np.array_equal(a, b) for a, b in zip(fitted, _states(later)))
    # the later cache fitted nothing: it asked its source only for each file's check (3 epochs a pair)
    assert sum(asked) <= 3 * len(PAIRS) and len(asked) == len(PAIRS)
    # and a cache without a store gives the same bits
    assert all(np.array_equal(a, b) for a, b in zip(fitted, _states(EphemerisCache(Ephemeris()))))


def _stored(tmp_path, body="mars", center="sun"):
    """A store holding two days of one pair's segments, and that pair's file."""
    store = SegmentStore(tmp_path)
    cache = EphemerisCache(Ephemeris(), store=store)
    cache.state(body, EPOCHS, center=center)
    cache.save()
    key = pair_key(source_identity(cache.ephemeris), body, center, cache.segment_length(body, center), cache.degree)
    return store, store.path(key), key


def _fits_again_and_answers_exactly(store, body="mars", center="sun"):
    source, asked = _counting_source()
    cache = EphemerisCache(source, store=store)
    r, v = cache.state(body, EPOCHS, center=center)
    r_ref, v_ref = Ephemeris().state(body, EPOCHS, center=center)
    assert np.abs(r - r_ref).max() < 1e-5 and np.abs(v - v_ref).max() < 1e-9
    assert any(n == cache.degree + 1 for n in asked)  # segments fitted at their nodes
    return cache


@pytest.mark.parametrize("damage", ["truncated", "flipped byte", "not a zip"])
def test_a_damaged_file_is_fitted_again_and_replaced(tmp_path, damage):
    store, path, key = _stored(tmp_path)
    data = path.read_bytes()
    if damage == "truncated":
        path.write_bytes(data[: len(data) // 2])
    elif damage == "flipped byte":
        path.write_bytes(data[:-200] + bytes([data[-200] ^ 0xFF]) + data[-199:])
    else:
        path.write_text("not an npz")
    cache = _fits_again_and_answers_exactly(store)
    cache.save()
    assert store.load(key, cache.degree, cache.segment_length("mars", "sun"),
                      lambda t: np.hstack(Ephemeris().state("mars", t, center="sun")))


def test_a_whole_file_whose_series_disagree_with_the_source_is_not_used(tmp_path):
    """Checksum and key right, but the coefficients of another model (here 10 cm off in x): the check
    against the exact source refuses the file."""
    store, path, key = _stored(tmp_path)
    with np.load(path) as data:
        index, coefficients = data["index"], data["coefficients"].copy()
    coefficients[:, 0, 0] += 10 * CHECK_POSITION_KM
    np.savez(path, key=np.str_(key), index=index, coefficients=coefficients,
             checksum=np.str_(_checksum(index, coefficients)))
    _fits_again_and_answers_exactly(store)


def test_another_pairs_file_under_this_name_is_not_used(tmp_path):
    store, path, _ = _stored(tmp_path)
    _, other, _ = _stored(tmp_path, "deimos", "ssb")
    other.replace(path)
    _fits_again_and_answers_exactly(store)


def test_saves_keep_what_the_file_holds_and_unnamed_sources_are_not_stored(tmp_path):
    store = SegmentStore(tmp_path)
    early, late = EphemerisCache(Ephemeris(), store=store), EphemerisCache(Ephemeris(), store=store)
    early.state("mars", T0 + 100.0, center="sun")
    late.state("mars", T0 + 30 * 86_400.0, center="sun")
    early.save()
    late.save()
    (path,) = tmp_path.glob("*.npz")
    with np.load(path) as data:
        assert data["index"].size == 2

    class Shifted(Ephemeris):  # a source the store cannot name
        pass

    cache = EphemerisCache(Shifted(), store=SegmentStore(tmp_path / "other"))
    cache.state("mars", T0, center="sun")
    cache.save()
    assert not (tmp_path / "other").exists()
