"""The solver's noise model from a FITS header: all three keywords used, anything else fitted from the frame."""

import logging

from opnav.image.plate_solve import _header_noise


def test_a_header_with_the_noise_model_gives_it():
    header = {"RDNOISE": 8.0, "GAIN": 2.0, "BIASLVL": 100.0}
    assert _header_noise(header, "f.fits") == {"read_noise_e": 8.0, "gain_e_per_adu": 2.0, "bias_adu": 100.0}


def test_a_partial_or_absent_noise_model_is_fitted_from_the_frame():
    assert _header_noise(None, "f.fits") is None
    assert _header_noise({"RDNOISE": 8.0, "GAIN": 2.0}, "f.fits") is None


def test_an_unusable_keyword_is_a_warning_naming_it(caplog):
    with caplog.at_level(logging.WARNING):
        assert _header_noise({"RDNOISE": 8.0, "GAIN": "high", "BIASLVL": 100.0}, "f.fits") is None
        assert _header_noise({"RDNOISE": 8.0, "GAIN": 0.0, "BIASLVL": 100.0}, "f.fits") is None
    assert "f.fits: FITS keyword GAIN must be a number" in caplog.text
    assert "GAIN 0.0" in caplog.text
