"""Tracking mode of the image stage against the full-frame stage and against the frames' truth."""

from dataclasses import replace

import numpy as np
import pytest
from scipy.stats import chi2
from scipy.spatial.transform import Rotation

from opnav.sim.checks import radec_errors
from opnav.errors import InputError
from opnav.image.pipeline import PipelineOptions, frame_input, measure_frame
from opnav.image.tracking import Tracker, TrackingOptions, track_frame

FRAMES = 12
STEP_S = 60.0


@pytest.fixture(scope="module")
def s1_frames(s1_demo_frames):
    """Twelve S1 demo frames a minute apart (Phobos-tracking 1-degree camera, both moons, Mars;
    16 July: both moons clear of Mars' glare), rendered once per session (tests/conftest.py)."""
    frames = s1_demo_frames[0]
    assert len(frames.paths) == FRAMES and np.allclose(np.diff([t.t_tdb_s for t in frames.truths]), STEP_S)
    return s1_demo_frames


def test_tracking_gives_the_full_frame_records_and_never_a_wrong_star(s1_frames):
    frames, catalog, ephemeris, options = s1_frames
    inputs = [frame_input(path) for path in frames.paths]
    full = [measure_frame(f, catalog=catalog, ephemeris=ephemeris, options=options, rng=k) for k, f in enumerate(inputs)]
    tracker = Tracker(catalog, ephemeris, options)
    tracked = [tracker.step(f, rng=k) for k, f in enumerate(inputs)]
    assert [e["event"] for e in tracker.events] == ["acquired"]  # one acquisition, then tracking throughout
    full_records = {(r.frame_id, r.target): r for res in full for r in res.records}
    tracked_records = {(r.frame_id, r.target): r for res in tracked for r in res.records}
    assert tracked_records.keys() == full_records.keys() and len(full_records) >= FRAMES
    stars = {res.frame_id: res.n_stars_matched for res in full}
    tracked_stars = {res.frame_id: res.n_stars_matched for res in tracked}
    for key, record in tracked_records.items():
        reference = full_records[key]
        sigma = np.sqrt(np.diag(reference.covariance))
        difference = record.value - reference.value
        if stars[key[0]] == tracked_stars[key[0]]:
            # same pixels, same centroid fit, same stars: the same record
            assert np.all(np.abs(difference) < 0.05 * sigma), key
        else:
            # the attitude rests on one star more or less (the full-frame stage drops blended
            # detections); two nested estimates differ by noise with the covariance of what the
            # poorer one lacks
            lacking = reference.covariance - record.covariance
            if stars[key[0]] > tracked_stars[key[0]]:
                lacking = -lacking
            assert np.all(np.linalg.eigvalsh(lacking) > 0), key
            assert difference @ np.linalg.solve(lacking, difference) < chi2.ppf(0.999, 2), key
        np.testing.assert_allclose(np.sqrt(np.diag(record.covariance)), sigma, rtol=0.5)
    truths = {path.stem: truth for path, truth in zip(frames.paths, frames.truths)}
    errors = radec_errors([r for res in tracked for r in res.records], truths)
    for name, entry in errors.items():
        assert np.mean(entry["chi2"]) < 2.0 + 4.0 * np.sqrt(4.0 / entry["count"]), name  # chi-square(2) mean
    # every star the attitude used is the catalog star the truth put there
    for path, truth in zip(frames.paths[1:], frames.truths[1:]):
        prior = frame_input(path)
        result = track_frame(prior, catalog=catalog, ephemeris=ephemeris, options=options)
        where = dict(zip(truth.stars.star_id.tolist(), truth.stars.xy_px))
        used = np.flatnonzero(result.used)
        assert used.size >= 3
        for i in used:
            star = int(result.predicted.star_id[i])
            assert np.hypot(*(result.centroids.xy[i] - where[star])) < 0.5, (path.name, star)


def test_a_wrong_prior_loses_lock_and_the_tracker_reacquires(s1_frames):
    frames, catalog, ephemeris, options = s1_frames
    frame = frame_input(frames.paths[0])
    off = replace(frame, R_prior=frame.R_prior * Rotation.from_rotvec([4e-4, 0.0, 0.0]))  # ~24 px
    result = track_frame(off, catalog=catalog, ephemeris=ephemeris, options=options)
    assert result.result is None and "predicted stars found" in result.lost
    tracker = Tracker(catalog, ephemeris, options)
    tracker.step(frame)
    tracker._last = [(t, R * Rotation.from_rotvec([4e-4, 0.0, 0.0])) for t, R in tracker._last]  # a bad carry-forward
    result = tracker.step(frame_input(frames.paths[1]))
    assert [e["event"] for e in tracker.events] == ["acquired", "lost", "acquired"]
    assert result.n_stars_matched >= 3 and "attitude_prior" not in result.flags


def test_a_star_that_is_not_there_is_reported_missing_not_matched(s1_frames):
    frames, catalog, ephemeris, options = s1_frames
    frame = frame_input(frames.paths[2])
    clean = track_frame(frame, catalog=catalog, ephemeris=ephemeris, options=options)
    star = int(np.flatnonzero(clean.found)[0])
    x, y = np.rint(clean.predicted.xy_px[star]).astype(int)
    image = frame.image.copy()
    image[y - 6:y + 7, x - 6:x + 7] = np.median(image)  # the star is gone (e.g. a catalog error)
    result = track_frame(replace(frame, image=image), catalog=catalog, ephemeris=ephemeris, options=options)
    assert clean.predicted.star_id[star] in result.missing_star_ids
    assert not result.used[star] and result.result is not None


def test_guide_stars_with_a_catalog_neighbour_are_left_out(s1_frames):
    """neighbour_depth_mag: a star with another catalog star (to the stage's limit plus the depth)
    within neighbour_radius_px is not predicted; every other star still is."""
    from opnav.image.tracking import predict_stars

    frames, catalog, _, options = s1_frames
    frame = frame_input(frames.paths[0])
    every = predict_stars(frame, catalog, {}, options, TrackingOptions())
    camera, R, observer = frame.camera, frame.R_prior, frame.observer
    rows = catalog.cone(R.apply([0.0, 0.0, 1.0]), camera.half_diagonal_fov_rad * 1.05, vmag_limit=options.vmag_limit + 3.0)
    deep = camera.project(R.inv().apply(catalog.apparent_directions(
        rows, t_tdb_s=frame.t_tdb_s, r_observer_ssb_km=observer.r_ssb_km, v_observer_ssb_km_s=observer.v_ssb_km_s)))
    nearest = np.sort(np.hypot(*(every.xy_px[:, None, :] - deep[None, :, :]).transpose(2, 0, 1)), axis=1)[:, 1]
    radius = float(np.median(nearest))  # a radius that leaves some stars crowded and some clear
    crowded = nearest <= radius
    assert 0 < crowded.sum() < len(every.rows)
    guides = predict_stars(frame, catalog, {}, options, TrackingOptions(neighbour_depth_mag=3.0,
                                                                        neighbour_radius_px=radius))
    assert set(guides.star_id.tolist()) == set(every.star_id[~crowded].tolist())


def test_tracking_options_are_checked():
    with pytest.raises(InputError, match="search_px"):
        TrackingOptions(search_px=0.0)
    with pytest.raises(InputError, match="min_stars"):
        TrackingOptions(min_stars=1)
    with pytest.raises(InputError, match="neighbour_depth_mag"):
        TrackingOptions(neighbour_depth_mag=-1.0)


def test_resolved_bodies_are_refused_before_any_work(s1_frames):
    frames, catalog, ephemeris, _ = s1_frames
    with pytest.raises(InputError, match="full-frame stage"):
        track_frame(frame_input(frames.paths[0]), catalog=catalog, ephemeris=ephemeris,
                    options=PipelineOptions(targets=("phobos", "mars")))
