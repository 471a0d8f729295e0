"""CCSDS files a run writes, as other readers see them (issue 36 item 3): the spacecraft named in
the OEMs and the TDM, INTERPOLATION in the OEMs, TDMs the ``ccsds-ndm`` parser reads with the same
numbers, a ``radec_pair``'s cross-covariance kept beside the TDM, and the demo's TDM navigating to the
CSV's estimate. ``benchmarks/ccsds_readers.py`` adds the second independent reader (``ccsds-ndm-py``)."""

from __future__ import annotations

import pytest

from opnav.errors import InputError
from opnav.studies.settings import load_run_file

RUN = """[scenario]
study = "s1"
name = "cruise"
{extra}
[settings]
month = "jul"
"""


def test_the_spacecraft_is_the_run_files_or_its_name(tmp_path):
    named = tmp_path / "named.toml"
    named.write_text(RUN.format(extra='spacecraft = "MAVEN"'))
    plain = tmp_path / "plain.toml"
    plain.write_text(RUN.format(extra=""))
    run = load_run_file(named)
    assert run.spacecraft == "MAVEN" and run.describe()["spacecraft"] == "MAVEN"
    default = load_run_file(plain)
    # the default leaves the run's identity (its stage hashes) as it was
    assert default.spacecraft == "cruise" and "spacecraft" not in default.describe()


@pytest.mark.parametrize("value", ['" MAVEN"', '""', '"MA\\nVEN"'])
def test_a_spacecraft_name_a_ccsds_file_cannot_hold_is_refused(tmp_path, value):
    path = tmp_path / "bad.toml"
    path.write_text(RUN.format(extra=f"spacecraft = {value}"))
    with pytest.raises(InputError) as caught:
        load_run_file(path)
    message = str(caught.value)
    assert str(path) in message and "[scenario] spacecraft" in message and "\n" not in message
