"""CCSDS writers against golden files: the bytes of a written OEM and TDM do not change.

The files in ``tests/golden/ccsds`` were written by the writers of opnav before they were
vectorised (epochs formatted one array at a time, messages built only on failure); the same
inputs must give the same bytes, in KVN and XML. Only ``CREATION_DATE`` (the wall clock) is held
fixed. Written again deliberately for issue 36 (TDM segments per sensor and target with the
covariances in the sidecar ``*.cov.csv``, no blank line before ``DATA_START``, ``INTERPOLATION`` in
the OEMs); every ANGLE line and every OEM data line kept its bytes. To write them again after a deliberate format change::

    .venv/bin/python tests/test_ccsds_golden.py
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest

from opnav import ccsds
from opnav.ccsds import oem as _oem, tdm as _tdm  # noqa: F401 (the writers' modules, patched below)
from opnav.records import Measurement

GOLDEN = Path(__file__).parent / "golden" / "ccsds"
CREATION_DATE = "2026-11-28T00:00:00"
FILES = ("radec.tdm", "radec.tdm.cov.csv", "radec.xml", "radec.xml.cov.csv", "arc.oem", "arc_cov.oem",
         "arc_cov.xml")


def radec_records() -> list[Measurement]:
    """Records that touch every formatting path: several segments (sensor, target, covariance), a sensor
    left out, right ascensions that wrap (a tiny negative one must become 0, not 360), declinations
    near the poles, epochs half a microsecond from a rounding edge, long ago and far ahead, and
    records given out of time order; a record of another kind is skipped."""
    rng = np.random.default_rng(11)
    covs = [np.array([[1e-10, 2e-12], [2e-12, 4e-10]]), np.diag([2.5e-9, 2.5e-9]), np.diag([1.0e-12, 3.0e-12])]
    epochs = list(4.5e8 + np.cumsum(rng.uniform(0.5, 90.0, 24)))
    epochs += [4.5e8 + 0.0000005, 4.5e8 + 1.0000004999, 4.5e8 + 2.9999995, -1.5e9 + 0.25, 4.7e9 + 0.125, 0.0]
    ras = list(rng.uniform(0.0, 2.0 * math.pi, 24)) + [-1e-18, 2.0 * math.pi - 1e-13, 1e-300, math.pi, 0.0, 6.2]
    decs = list(rng.uniform(-1.5, 1.5, 24)) + [0.5 * math.pi, -0.5 * math.pi, -1e-9, 0.0, 1.2345678901234567, -0.7]
    records = []
    for k, (t, ra, dec) in enumerate(zip(epochs, ras, decs)):
        target = ("phobos", "deimos", "mars")[k % 3]
        sensor = ("nac", "wac", "")[(k // 3) % 3]
        records.append(Measurement(float(t), "radec", [ra, dec], covs[(k // 5) % 3], target=target, sensor=sensor))
    records.reverse()
    records.insert(3, Measurement(4.5e8, "position", [1.0, 2.0, 3.0], np.eye(3)))
    return records


def ephemeris(n: int = 25) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Epochs (off whole microseconds, one half a microsecond from a rounding edge), states, covariances."""
    rng = np.random.default_rng(12)
    t = 4.5e8 + np.cumsum(rng.uniform(0.5, 120.0, n))
    t[3] = math.floor(t[3]) + 0.0000005
    states = np.hstack([rng.normal(scale=5000.0, size=(n, 3)), rng.normal(scale=2.0, size=(n, 3))])
    states[0, 0], states[1, 1], states[2, 2] = 1e-300, -0.0, 123456789.123456789
    a = rng.normal(size=(n, 6, 6))
    cov = a @ np.swapaxes(a, 1, 2) * np.outer([1.0] * 3 + [1e-3] * 3, [1.0] * 3 + [1e-3] * 3)
    return t, states, 0.5 * (cov + np.swapaxes(cov, 1, 2))


def write_all(folder: Path) -> None:
    """Write the golden messages into ``folder`` with the writers of the tree."""
    records = radec_records()
    t, states, cov = ephemeris()
    ccsds.write_tdm(folder / "radec.tdm", records, participant="mro")
    ccsds.write_tdm(folder / "radec.xml", records, originator="golden")
    ccsds.write_oem(folder / "arc.oem", t, states, comment="golden arc\nno covariance")
    ccsds.write_oem(folder / "arc_cov.oem", t, states, cov, center="PHOBOS", ref_frame="EME2000")
    ccsds.write_oem(folder / "arc_cov.xml", t, states, cov, object_name="probe", object_id="2026-001A")


def _fixed_creation_date(monkeypatch) -> None:
    for module in (ccsds.oem, ccsds.tdm):
        monkeypatch.setattr(module, "creation_time_utc", lambda: CREATION_DATE)


@pytest.mark.parametrize("name", FILES)
def test_written_files_are_byte_identical_to_the_golden_ones(tmp_path, monkeypatch, name):
    _fixed_creation_date(monkeypatch)
    write_all(tmp_path)
    assert (tmp_path / name).read_bytes() == (GOLDEN / name).read_bytes()


if __name__ == "__main__":
    GOLDEN.mkdir(parents=True, exist_ok=True)
    ccsds.oem.creation_time_utc = ccsds.tdm.creation_time_utc = lambda: CREATION_DATE
    write_all(GOLDEN)
    print(f"golden files written to {GOLDEN}", file=sys.stderr)
