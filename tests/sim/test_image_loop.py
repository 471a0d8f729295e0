"""The in-memory image loop: windowed frames measured like full ones, chunks resumed exactly."""

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from opnav.cli import main
from opnav.sim.checks import pair_chi2, radec_errors
from opnav.ephemeris.cache import default_cached_ephemeris
from opnav.image.pipeline import PipelineOptions
from opnav.sim.scene import observer_states
from opnav.studies.image_loop import stream_frames
from opnav.studies.s1 import MOONS, load_demo

FRAMES = 25
S1 = str(Path(__file__).resolve().parents[2] / "samples" / "s1_jul_both_0.1.toml")


@pytest.fixture(scope="module")
def arc():
    scenario, _, _ = load_demo()
    ephemeris = default_cached_ephemeris()
    t = scenario.t_tdb_s[0] + 86_400.0 + 60.0 * np.arange(FRAMES)
    r, v = observer_states(replace(scenario, t_tdb_s=t), t, ephemeris)
    return replace(scenario, t_tdb_s=t), t, r, v


def _stream(arc, out, key="test", **options):
    scenario, t, r, v = arc
    return stream_frames(scenario, t, r, v, out, seed=5,
                         options=PipelineOptions(targets=MOONS, vmag_limit=scenario.options.vmag_limit),
                         moons=MOONS, progress=False, key=key, **options)


def _records(result):
    return [(r.frame_id, r.t_tdb_s, r.target, r.value.tolist(), r.covariance.tolist()) for r in result.records]


@pytest.fixture(scope="module")
def streamed(arc, tmp_path_factory):
    """The arc streamed once in this process in chunks of 10 frames: its folder and result (tests
    that change the folder work on a copy)."""
    out = tmp_path_factory.mktemp("streamed")
    return out, _stream(arc, out, chunk_frames=10)


def test_windowed_frames_give_consistent_records_and_chunks_resume_exactly(arc, streamed, tmp_path):
    import shutil

    shutil.copytree(streamed[0], tmp_path / "a")
    whole = streamed[1]
    # each chunk acquires on its first frame, then reads windows only
    assert whole.frames_full == 3 and whole.frames_windowed == FRAMES - 3
    assert [e["event"] for e in whole.events] == ["acquired"] * 3
    # every star the tracked frames' attitudes used is where the truth put that catalog star
    assert whole.stars_used >= 3 * whole.frames_windowed and whole.stars_misidentified == 0
    errors = radec_errors(whole.records, whole.truths)
    assert set(errors) == set(MOONS)
    for name, entry in errors.items():
        # the reported covariance explains the errors against the rendered truth: chi-square(2) mean
        assert np.mean(entry["chi2"]) < 2.0 + 4.0 * np.sqrt(4.0 / entry["count"]), name
    # a frame with both moons gives one record whose cross-covariance is their shared attitude error;
    # with it the pair's errors are chi-square(4)
    pairs = pair_chi2(whole.records, whole.truths)
    assert pairs.size == sum(r.kind == "radec_pair" for r in whole.records) >= FRAMES // 5
    assert np.mean(pairs) < 4.0 + 4.0 * np.sqrt(8.0 / pairs.size)
    # an interrupted run: the last chunk never finished; the re-run reads the first two and redoes it
    (tmp_path / "a" / "stream" / "chunk_00002.done.json").unlink()
    resumed = _stream(arc, tmp_path / "a", chunk_frames=10)
    assert resumed.chunks_reused == 2
    assert _records(resumed) == _records(whole)
    # a chunk whose records were damaged after it finished is made again, to the same records
    damaged = tmp_path / "a" / "stream" / "chunk_00001.records.csv"
    damaged.write_text(damaged.read_text().replace("phobos", "deimos", 1))
    repaired = _stream(arc, tmp_path / "a", chunk_frames=10)
    assert repaired.chunks_reused == 2
    assert _records(repaired) == _records(whole)
    # another run's chunks (another key) are not reused
    assert _stream(arc, tmp_path / "a", key="other", chunk_frames=10).chunks_reused == 0


def test_chunks_in_worker_processes_give_the_same_records(arc, streamed, tmp_path):
    one = streamed[1]
    two = _stream(arc, tmp_path / "two", chunk_frames=10, workers=2)
    assert two.chunks_reused == 0 and len(two.records) > 0
    assert _records(two) == _records(one)
    assert two.events == one.events and two.truths == one.truths


def test_every_nth_frame_is_written_for_inspection(arc, tmp_path):
    result = _stream(arc, tmp_path, dump_every=10, chunk_frames=100)
    assert [p.name for p in result.paths] == ["frame_00000.fits", "frame_00010.fits", "frame_00020.fits"]
    assert all(p.exists() and p.with_suffix(".truth.json").exists() for p in result.paths)


def test_s1_image_mode_in_memory_from_the_command_line(tmp_path):
    out = tmp_path / "run"
    assert main(["run", S1, "--mode", "images", "--set", "duration_days=0.01",
                 "--set", "day=16", "--set", "dump_every=0", "--filters", "ekf", "--out", str(out),
                 "--no-progress"]) == 0
    facts = json.loads((out / "summary.json").read_text())["facts"]
    assert facts["frames"] == 14 and facts["frames_windowed"] == 13 and facts["frames_on_disk"] == 0
    assert facts["tracking"]["acquisitions"] == 1 and facts["tracking"]["losses_of_lock"] == 0
    assert not (out / "frames").exists()
    assert main(["run", S1, "--mode", "images", "--set", "dump_every=0",
                 "--set", "image_stage=full-frame", "--out", str(tmp_path / "bad"), "--no-progress"]) == 2


def _unidentified_frames_limit(monkeypatch, limit: int) -> None:
    """The streamed runs' tracking stages stop after ``limit`` unidentified frames instead of
    MAX_UNIDENTIFIED_FRAMES (for the fast siblings: a few frames instead of 70 to 90)."""
    from functools import partial

    from opnav.sim.stages import Tracking
    from opnav.studies import image_loop

    monkeypatch.setattr(image_loop, "Tracking", partial(Tracking, max_unidentified_frames=limit))


def _mirrored_camera_stops_the_run(tmp_path, limit: int, capsys):
    # frames mirrored left to right: no frame's stars match the catalog through the camera model;
    # the run stops with one clear line after `limit` frames, never navigates on them
    out = tmp_path / "flipped"
    args = ["run", S1, "--mode", "images", "--set", "day=16", "--set", "dump_every=0", "--filters", "ekf",
            "--set", f"duration_days={(limit + 10) / 1440}", "--workers", "1", "--no-progress",
            "--out", str(out)]
    capsys.readouterr()
    assert main(args + ["--set", "faults.flipped_axis=true"]) == 2
    assert f"star identification gave no attitude on {limit} frames" in capsys.readouterr().err
    assert not (out / "summary.json").exists()


@pytest.mark.slow
def test_a_mirrored_camera_stops_the_run_instead_of_navigating(tmp_path, capsys):
    from opnav.sim.stages import MAX_UNIDENTIFIED_FRAMES

    _mirrored_camera_stops_the_run(tmp_path, MAX_UNIDENTIFIED_FRAMES, capsys)


def test_a_mirrored_camera_stops_the_run_after_the_unidentified_frames_limit(tmp_path, monkeypatch, capsys):
    """Fast sibling of the test above: the stage's limit set to 5 frames (15 rendered, not 70)."""
    _unidentified_frames_limit(monkeypatch, 5)
    _mirrored_camera_stops_the_run(tmp_path, 5, capsys)
    # frame faults act on rendered frames only
    assert main(["run", S1, "--set", "faults.cosmic_ray_factor=10", "--set", "duration_days=0.1", "--no-progress",
                 "--out", str(tmp_path / "measurements")]) == 2


def test_frame_faults_are_applied_and_listed(arc, tmp_path):
    from opnav.studies.faults import Faults

    scenario = arc[0]
    faults = Faults(dropped_frame_fraction=0.2, hot_pixel_clusters=50, cosmic_ray_factor=10.0, stray_light_e=500.0,
                    uncatalogued_stars=3, missing_star_fraction=0.1, prior_attitude_error_arcsec=30.0)
    clean = _stream(arc, tmp_path / "clean")
    faulted = _stream(arc, tmp_path / "faulted", faults=faults)
    lost = [frame for frame, reason in faulted.skipped.items() if "dropped_frame_fraction" in reason]
    assert faulted.frames_dropped == len(lost) > 0
    assert faulted.frames_windowed + faulted.frames_full + faulted.frames_dropped == FRAMES
    assert _records(faulted) != _records(clean)
    # what the stage still measured is explained by its covariance
    for name, entry in radec_errors(faulted.records, faulted.truths).items():
        assert np.mean(entry["chi2"]) < 2.0 + 4.0 * np.sqrt(4.0 / entry["count"]), name
    assert scenario.options.stray_light_e == 0.0  # the scenario itself is untouched


def test_a_tracked_star_away_from_its_truth_counts_as_misidentified():
    from types import SimpleNamespace

    from opnav.sim.checks import misidentified_stars

    truth = SimpleNamespace(star_id=np.array([10, 11, 12]), xy_px=np.array([[5.0, 5.0], [50.0, 60.0], [90.0, 9.0]]))
    tracked = SimpleNamespace(used=np.array([True, True, True, False]),
                              predicted=SimpleNamespace(star_id=np.array([10, 11, 13, 12])),
                              centroids=SimpleNamespace(xy=np.array([[5.1, 4.9], [51.5, 60.0], [0.0, 0.0], [0.0, 0.0]])))
    # star 11 is 1.5 px from its truth, star 13 is not in the frame's truth; star 12 is not used
    assert misidentified_stars(tracked, truth) == (3, 2)


@pytest.mark.slow
def test_a_sparse_field_is_not_taken_for_a_camera_fault(tmp_path):
    # 18 August: the field holds 2-3 catalog stars beside Mars for the first frames of the day, too few
    # to identify; the run goes on (attitude from the prior, flagged) instead of stopping as for a
    # mirrored camera, and acquires once the stars are back
    out = tmp_path / "sparse"
    status = main(["run", S1, "--mode", "images", "--set", "month=aug", "--set", "day=18", "--set", "dump_every=0",
                   "--set", "duration_days=0.06", "--filters", "ekf", "--workers", "1", "--no-progress",
                   "--out", str(out)])
    assert status in (0, 3)
    facts = json.loads((out / "summary.json").read_text())["facts"]
    assert facts["tracking"]["failed_acquisitions"] > 0
    # those frames give no records: the a-priori attitude's 0.05 degrees would carry nothing
    unidentified = [f for f, reason in facts["frames_skipped"].items() if "no star-identified attitude" in reason]
    assert len(unidentified) == facts["tracking"]["failed_acquisitions"]
    records = (out / "measurements.csv").read_text()
    assert not any(f",{frame}," in records for frame in unidentified)


def test_a_sparse_field_is_not_counted_towards_the_unidentified_frames_limit(tmp_path, monkeypatch):
    """Fast sibling of the test above: the first 10 frames of 18 August (2-3 catalog stars beside
    Mars) streamed with the stage's limit at 5 frames: 10 failed acquisitions and the loop goes on;
    every frame is skipped for want of a star-identified attitude and gives no record."""
    from opnav.studies.s1 import arc_start
    from opnav.studies.settings import load_run_file

    _unidentified_frames_limit(monkeypatch, 5)
    settings = load_run_file(Path(S1), {"month": "aug", "day": "18"}).settings
    scenario, _, _ = load_demo()
    t = arc_start(settings) + 60.0 * np.arange(1, 11)
    r, v = observer_states(replace(scenario, t_tdb_s=t), t, default_cached_ephemeris())
    result = _stream((replace(scenario, t_tdb_s=t), t, r, v), tmp_path)
    assert [e["event"] for e in result.events] == ["acquisition failed"] * 10
    assert len(result.skipped) == 10 and all("no star-identified attitude" in why for why in result.skipped.values())
    assert result.records == ()


def test_moons_are_drawn_where_the_ephemeris_error_puts_them(arc, tmp_path):
    # the truth's moon ephemeris error (1 km per axis, a new draw per frame) moves what is drawn, not
    # what the stage predicts; the records still match the drawn moons within their covariance
    plain = _stream(arc, tmp_path / "plain")
    moved = _stream(arc, tmp_path / "moved", moon_ephemeris_sigma_km=1.0)
    shifts = [np.hypot(*(np.array(moved.truths[f].directions[m]) - np.array(plain.truths[f].directions[m])))
              for f in moved.truths for m in MOONS]
    assert 0.0 < np.median(shifts) < 1e-6  # radians: 1 km at tens of millions of km
    for name, entry in radec_errors(moved.records, moved.truths).items():
        assert np.mean(entry["chi2"]) < 2.0 + 4.0 * np.sqrt(4.0 / entry["count"]), name


def test_a_star_on_the_bloom_trail_of_mars_does_not_make_a_frame_identifiable():
    # 3 August 2014, 00:01 TDB: four catalog stars predicted, one of them on Mars' bloom trail and
    # Phobos behind Mars; star identification has three stars and fails. Counted as a frame it
    # should have solved, an hour of these stopped a 30-day run (seed 3) as if the camera were mirrored.
    from opnav.catalog import load_catalog
    from opnav.image.pipeline import FrameInput, measure_frame
    from opnav.image.tracking import TrackingOptions, predict_stars_at, views_with_primaries
    from opnav.observer import Observer
    from opnav.render.frame import render_frame
    from opnav.render.frames_io import saturation_level_adu
    from opnav.sim.pointing import body_rate, pointing_attitude
    from opnav.sim.stages import IDENTIFIABLE_STARS, identifiable
    from opnav.studies.s1 import arc_start
    from opnav.studies.settings import load_run_file

    settings = load_run_file(Path(S1), {"month": "aug", "day": "3"}).settings
    scenario, _, _ = load_demo()
    ephemeris = default_cached_ephemeris()
    catalog = load_catalog(scenario.catalog_path)
    t = np.array([arc_start(settings) + 60.0])
    r, v = observer_states(replace(scenario, t_tdb_s=t), t, ephemeris)
    observer = Observer(float(t[0]), r[0], v[0])
    corrections = scenario.options.corrections
    attitude = pointing_attitude(scenario.pointing, observer, ephemeris, corrections)
    rendered = render_frame(scenario.camera, attitude, observer, catalog=catalog, targets=scenario.targets,
                            ephemeris=ephemeris, options=scenario.options,
                            omega_cam_rad_s=body_rate(scenario.pointing, observer, ephemeris, corrections),
                            rng=np.random.default_rng([3, 2880]))
    frame = FrameInput.from_camera(rendered.image, scenario.camera, float(t[0]), attitude, observer,
                                   saturation_adu=saturation_level_adu(scenario.camera))
    options = PipelineOptions(targets=MOONS, vmag_limit=scenario.options.vmag_limit)
    result = measure_frame(frame, catalog=catalog, ephemeris=ephemeris, options=options, rng=0)
    assert "attitude_prior" in result.flags  # identification failed
    views = views_with_primaries(frame.camera, attitude, observer, ephemeris, MOONS)
    predicted = predict_stars_at(frame.camera, frame.t_tdb_s, observer, attitude, catalog, views, options,
                                 TrackingOptions())
    assert len(predicted.rows) >= IDENTIFIABLE_STARS  # predicted, but one lies on the trail
    assert not identifiable(frame, result, catalog, ephemeris, options, TrackingOptions())
