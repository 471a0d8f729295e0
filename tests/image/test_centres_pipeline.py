"""The image stage's ``centre_finding="by_size"`` option: a resolved Mars measured by the chooser's
method (records inside 3 sigma of the truth), and today's by-name behaviour left as it was."""

import math

import numpy as np
import pytest
from scipy.stats import chi2

from centre_scene import render_scene
from opnav.errors import InputError
from opnav.image.centres import CentreOptions
from opnav.image.pipeline import FrameInput, PipelineOptions, measure_frame
from opnav.measurements import ProbeMeasurementModel


def _frame(scene):
    return FrameInput.from_camera(scene.image, scene.camera, scene.observer.t_tdb_s, scene.R_icrf_cam, scene.observer)


@pytest.mark.parametrize("diameter, phase, method", [(60, 45, "limb"), (14, 60, "correlation")])
def test_by_size_measures_mars_by_its_apparent_size(diameter, phase, method):
    rng = np.random.default_rng(11)
    scene = render_scene("mars", diameter, phase, rng=rng, peak_e=3000.0, supersample=4)
    # the attitude is the truth, known to 1 nrad: the records' error is the centre finding's alone
    options = PipelineOptions(targets=("mars",), centre_finding="by_size", prior_sigma_rad=1e-9,
                              centre_options=CentreOptions(limb_min_diameter_px=20.0))
    # no stars in these frames: the model's PSF is unknown, and the frame says so
    result = measure_frame(_frame(scene), ephemeris=scene.ephemeris, options=options)
    assert not result.records and "no_mars" in result.flags
    from opnav.image import pipeline

    # with the PSF from the caller (as for a crop: target_records' psf_sigma_px)
    views = pipeline._target_views(_frame(scene), scene.ephemeris, options, "test")
    found = pipeline.measure_sources(_frame(scene), options)
    flags = []
    records = pipeline.target_records(_frame(scene), views, found, np.zeros(len(found.det), bool), scene.R_icrf_cam,
                                      np.eye(3) * 1e-18, None, scene.ephemeris, options, None, "test", flags,
                                      psf_sigma_px=scene.psf_sigma_px)
    assert not flags
    assert {r.extra.get("method") for r in records} == {method}
    assert {r.kind for r in records} == ({"radec", "target_vector"} if method == "limb" else {"radec"})
    model = ProbeMeasurementModel("ssb", ephemeris=scene.ephemeris)
    x = np.concatenate([scene.observer.r_ssb_km, scene.observer.v_ssb_km_s])
    for rec in records:
        resid = model.residual(rec, model.predict(rec, x))
        assert resid @ np.linalg.solve(rec.covariance, resid) < chi2.ppf(0.9973, rec.size), (rec.kind, resid)


def test_by_name_is_todays_limb_record():
    rng = np.random.default_rng(12)
    scene = render_scene("mars", 60, 45, rng=rng, supersample=8)
    result = measure_frame(_frame(scene), ephemeris=scene.ephemeris, options=PipelineOptions(targets=("mars",)))
    assert [r.kind for r in result.records] == ["los"]
    assert math.isclose(np.linalg.norm(result.records[0].value), 1.0, rel_tol=1e-12)


def test_unknown_centre_finding_is_refused_naming_the_choices():
    with pytest.raises(InputError, match="centre_finding must be one of by_name, by_size"):
        PipelineOptions(centre_finding="hough")
