"""Every study declares what it is, and holds what it declares."""

import types

import pytest

from opnav.studies import STUDIES
from opnav.studies.base import ModuleStudy, Study, check_study


@pytest.mark.parametrize("name", sorted(STUDIES))
def test_each_study_holds_what_it_declares(name):
    study = STUDIES[name]
    assert isinstance(study, Study)
    check_study(study)


def test_the_kinds_are_as_published():
    assert [n for n in sorted(STUDIES) if STUDIES[n].generic_filters] == ["mission", "s1", "s3"]
    # S2 from pixels (issue 37 item 3); S4's image mode is another helper's (item 4)
    assert {"s1", "s2", "s3"} <= {n for n in STUDIES if STUDIES[n].image_mode}


def test_a_module_that_breaks_its_declaration_is_named(monkeypatch):
    import sys
    from dataclasses import dataclass

    @dataclass(frozen=True)
    class Settings:
        arc_days: float = 1.0

    fake = types.ModuleType("opnav_fake_study")
    fake.Settings, fake.KIND, fake.IMAGE_MODE, fake.IMAGE_SETTINGS = Settings, "simulating", False, ()
    monkeypatch.setitem(sys.modules, "opnav_fake_study", fake)
    with pytest.raises(TypeError, match="opnav_fake_study .simulating. lacks simulate, dynamics"):
        check_study(ModuleStudy("fake", "opnav_fake_study"))
    del fake.KIND
    with pytest.raises(TypeError, match="does not declare KIND"):
        ModuleStudy("fake", "opnav_fake_study").generic_filters
