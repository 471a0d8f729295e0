"""The in-memory image loop: windowed frames measured like full ones, chunks resumed exactly."""

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from opnav.catalog import load_catalog
from opnav.cli import main
from opnav.demo import MOONS, load_demo, radec_errors
from opnav.ephemeris.cache import default_cached_ephemeris
from opnav.image.pipeline import PipelineOptions
from opnav.image.tracking import Tracker
from opnav.scenario import observer_states
from opnav.scenarios.image_loop import stream_frames

FRAMES = 25
S1 = str(Path(__file__).resolve().parent.parent / "samples" / "s1_jul_both_0.1.toml")


@pytest.fixture(scope="module")
def arc():
    scenario, _, _ = load_demo()
    ephemeris = default_cached_ephemeris()
    t = scenario.t_tdb_s[0] + 86_400.0 + 60.0 * np.arange(FRAMES)
    r, v = observer_states(replace(scenario, t_tdb_s=t), t, ephemeris)
    return replace(scenario, t_tdb_s=t), t, r, v, load_catalog(scenario.catalog_path), ephemeris


def _stream(arc, out, **options):
    scenario, t, r, v, catalog, ephemeris = arc
    tracker = Tracker(catalog, ephemeris, PipelineOptions(targets=MOONS, vmag_limit=scenario.options.vmag_limit))
    return stream_frames(scenario, t, r, v, out, seed=5, catalog=catalog, ephemeris=ephemeris, tracker=tracker,
                         moons=MOONS, progress=False, key="test", **options)


def test_windowed_frames_give_consistent_records_and_chunks_resume_exactly(arc, tmp_path):
    whole = _stream(arc, tmp_path / "a", chunk_frames=10)
    assert whole.frames_full == 1 and whole.frames_windowed == FRAMES - 1  # one acquisition, then windows only
    assert [e["event"] for e in whole.events] == ["acquired"]
    errors = radec_errors(whole.records, whole.truths)
    assert set(errors) == set(MOONS)
    for name, entry in errors.items():
        # the reported covariance explains the errors against the rendered truth: chi-square(2) mean
        assert np.mean(entry["chi2"]) < 2.0 + 4.0 * np.sqrt(4.0 / entry["count"]), name
    # an interrupted run: the last chunk never finished; the re-run reads the first two and redoes it
    (tmp_path / "a" / "stream" / "chunk_00002.done.json").unlink()
    resumed = _stream(arc, tmp_path / "a", chunk_frames=10)
    assert resumed.chunks_reused == 2
    assert [(r.t_tdb_s, r.target, r.value.tolist()) for r in resumed.records] == [
        (r.t_tdb_s, r.target, r.value.tolist()) for r in whole.records]
    # another run's chunks (another key) are not reused
    scenario, t, r, v, catalog, ephemeris = arc
    other = stream_frames(scenario, t, r, v, tmp_path / "a", seed=5, catalog=catalog, ephemeris=ephemeris,
                          tracker=Tracker(catalog, ephemeris, PipelineOptions(targets=MOONS)), moons=MOONS,
                          progress=False, key="other", chunk_frames=10)
    assert other.chunks_reused == 0


def test_every_nth_frame_is_written_for_inspection(arc, tmp_path):
    result = _stream(arc, tmp_path, dump_every=10, chunk_frames=100)
    assert [p.name for p in result.dumped] == ["frame_00000.fits", "frame_00010.fits", "frame_00020.fits"]
    assert all(p.exists() and p.with_suffix(".truth.json").exists() for p in result.dumped)


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
