"""Where the pattern indexes are cached: OPNAV_CACHE, then XDG_CACHE_HOME, then ~/.cache; never an empty HOME."""

import pytest


def test_the_cache_folder_follows_opnav_cache_then_xdg_then_home_and_never_an_empty_home(monkeypatch, tmp_path):
    """HOME='' put a 728 MB index under /.cache: without an absolute folder to use, opnav refuses."""
    from opnav.errors import InputError
    from opnav.image.starid_index import default_cache_dir

    monkeypatch.setenv("OPNAV_CACHE", str(tmp_path / "mine"))
    assert default_cache_dir() == tmp_path / "mine"
    monkeypatch.setenv("OPNAV_CACHE", "")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert default_cache_dir() == tmp_path / "xdg" / "opnav"
    monkeypatch.setenv("XDG_CACHE_HOME", "relative/cache")
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    assert default_cache_dir() == tmp_path / "home" / ".cache" / "opnav"
    monkeypatch.setenv("HOME", "")
    with pytest.raises(InputError, match="HOME is ''; set OPNAV_CACHE"):
        default_cache_dir()
