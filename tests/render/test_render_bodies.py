"""Extended bodies: magnitudes, photocentre vs phase, resolved disks, Sun keep-out."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from render_helpers import StaticEphemeris, sphere_at_phase
from opnav.camera import Camera
from opnav.constants import AU_KM
from opnav.epochs import parse_epoch
from opnav.errors import FrameError
from opnav.render import Body, Corrections, DetectorOptions, Observer, RenderOptions, render_frame
from opnav.bodies import view_body
from opnav.photometry import SUN_VMAG_1AU

GEOMETRIC = Corrections(light_time=False, aberration=False)
NOISE_FREE = RenderOptions(detector=DetectorOptions(noise_free=True, hot_pixel_fraction=0.0), corrections=GEOMETRIC)


def _pointing_at(direction, roll_hint=(0.0, 0.0, 1.0)):
    z = direction / np.linalg.norm(direction)
    x = np.cross(roll_hint, z)
    x /= np.linalg.norm(x)
    return Rotation.from_matrix(np.column_stack([x, np.cross(z, x), z]))


def _view(phase, shading, camera, radius=100.0):
    ephem, r_obs = sphere_at_phase(phase)
    body = Body("ball", (radius,) * 3, 0.1, shading=shading)
    attitude = _pointing_at(ephem.positions["ball"] - r_obs)
    return view_body(body, camera, attitude, Observer(0.0, r_obs, np.zeros(3)), ephem, corrections=GEOMETRIC)


def test_zero_phase_sphere_has_the_geometric_albedo_magnitude():
    camera = Camera.from_fov(0.2, 128, 128)
    for shading in ("lommel-seeliger", "lambert"):
        view = _view(1e-4, shading, camera)
        # m = m_sun - 2.5 log10(p R^2 / (r^2 Delta^2)) with r = 1 au, Delta = 1e6 km.
        expected = SUN_VMAG_1AU - 2.5 * math.log10(0.1 * 100.0**2 / 1.0e6**2)
        assert view.vmag == pytest.approx(expected, abs=0.01)


def test_lambert_photocentre_offset_follows_the_analytic_law():
    camera = Camera.from_fov(0.2, 128, 128)
    for phase in (0.3, 0.8, 1.3, 1.8, 2.3):
        view = _view(phase, "lambert", camera)
        offset_r = np.linalg.norm(view.xy_photocentre_px - view.xy_cof_px) * camera.pixel_scale_rad * 1.0e6 / 100.0
        # Lambert sphere (e.g. Lindegren 1977): 3pi/16 sin a (1 + cos a) / (sin a + (pi - a) cos a).
        law = 3 * math.pi / 16 * math.sin(phase) * (1 + math.cos(phase)) / (math.sin(phase) + (math.pi - phase) * math.cos(phase))
        assert offset_r == pytest.approx(law, rel=0.02)


def test_photocentre_offset_grows_with_phase_and_points_to_the_sun():
    camera = Camera.from_fov(0.2, 128, 128)
    offsets = []
    for phase in np.linspace(0.1, 2.6, 8):
        view = _view(phase, "lommel-seeliger", camera)
        offsets.append(np.linalg.norm(view.xy_photocentre_px - view.xy_cof_px))
        lambert = _view(phase, "lambert", camera)
        # The limb-bright Lommel-Seeliger disk shifts less than a Lambert disk at the same phase.
        assert offsets[-1] < np.linalg.norm(lambert.xy_photocentre_px - lambert.xy_cof_px)
    assert np.all(np.diff(offsets) > 0)


def test_phobos_and_deimos_magnitudes_from_earth_near_2014_opposition():
    from opnav.ephemeris import default_ephemeris

    ephem = default_ephemeris()
    t = parse_epoch("2014-04-08T21:00:00", "utc")
    r_earth, v_earth = ephem.state("earth", t)
    mars = ephem.position("mars", t) - r_earth
    camera = Camera.from_fov(0.1, 64, 64, exposure_s=1.0)
    observer = Observer(t, r_earth, v_earth)
    mags = {}
    for name in ("phobos", "deimos"):
        from opnav.render import body_model

        view = view_body(body_model(name), camera, _pointing_at(mars), observer, ephem)
        mags[name] = view.vmag
    # Observed: Phobos V(1,0) = 11.8, Deimos 12.9 (Thomas et al.), i.e. ~11.8 and ~12.9 at this
    # opposition (r * Delta ~ 1.0 au^2); the ellipsoid model has no opposition surge.
    assert 11.0 < mags["phobos"] < 12.3
    assert 12.1 < mags["deimos"] < 13.4
    assert 0.8 < mags["deimos"] - mags["phobos"] < 1.6


def test_resolved_body_flux_and_centroid_in_the_image():
    camera = Camera.from_fov(0.4, 96, 96, exposure_s=0.01)
    ephem, r_obs = sphere_at_phase(0.9, distance_km=1.0e5)
    body = Body("ball", (60.0, 50.0, 40.0), 0.1, shading="lommel-seeliger")
    attitude = _pointing_at(ephem.positions["ball"] - r_obs)
    observer = Observer(0.0, r_obs, np.zeros(3))
    result = render_frame(camera, attitude, observer, targets=[body], ephemeris=ephem, options=NOISE_FREE)
    target = result.truth.target("ball")
    assert target.resolved and 10 < 2 * target.angular_radius_rad / camera.pixel_scale_rad < 30
    image = result.signal_e
    assert image.sum() == pytest.approx(target.electrons, rel=5e-3)
    yy, xx = np.mgrid[0 : image.shape[0], 0 : image.shape[1]]
    centroid = np.array([(image * xx).sum(), (image * yy).sum()]) / image.sum()
    assert np.all(np.abs(centroid - target.xy_photocentre_px) < 0.02)
    assert np.linalg.norm(target.xy_photocentre_px - target.xy_cof_px) > 1.0


@pytest.mark.parametrize("diameter_px", [1.1, 1.6, 2.4])
def test_a_body_a_few_pixels_across_is_drawn_with_its_light_at_its_photocentre(diameter_px):
    # Drawn as its pixels' light convolved with the PSF from each pixel's centre, a body of 1-2 px at phase
    # came out 0.09-0.11 px off its own photocentre; the offset repeats with the body's place in its pixel.
    camera = Camera.from_fov(0.4, 48, 48, exposure_s=0.01)
    distance_km = 1.0e5
    radius_km = 0.5 * diameter_px * camera.pixel_scale_rad * distance_km
    ephem, r_obs = sphere_at_phase(math.radians(60.0), distance_km=distance_km)
    body = Body("ball", (radius_km, 0.9 * radius_km, 0.8 * radius_km), 0.1, shading="lommel-seeliger")
    errors = []
    for offset_px in (0.0, 0.3, 0.6):  # the body at three places inside its pixel
        direction = ephem.positions["ball"] - r_obs
        attitude = _pointing_at(direction) * Rotation.from_rotvec([0.0, offset_px * camera.pixel_scale_rad, 0.0])
        result = render_frame(camera, attitude, Observer(0.0, r_obs, np.zeros(3)), targets=[body], ephemeris=ephem,
                              options=NOISE_FREE)
        target = result.truth.target("ball")
        assert target.resolved
        image = result.signal_e
        assert image.sum() == pytest.approx(target.electrons, rel=0.02)
        yy, xx = np.mgrid[0 : image.shape[0], 0 : image.shape[1]]
        centroid = np.array([(image * xx).sum(), (image * yy).sum()]) / image.sum()
        errors.append(centroid - target.xy_photocentre_px)
    assert np.max(np.abs(errors)) < 0.01, errors


def test_uv_earth_disk_is_centred_and_has_a_soft_limb():
    camera = Camera.from_fov(24.0, 160, 160, exposure_s=0.1)
    r_geo = 42_164.0
    ephem = StaticEphemeris({"earth": np.array([AU_KM, 0.0, 0.0])})
    r_obs = ephem.positions["earth"] + np.array([0.0, r_geo, 0.0])
    attitude = _pointing_at(ephem.positions["earth"] - r_obs, roll_hint=(1.0, 0.0, 0.0))
    body = Body("earth", (6378.1363,) * 3, shading="uv-limb", uv_radiance_e_s_px=1.0e5)
    result = render_frame(camera, attitude, Observer(0.0, r_obs, np.zeros(3)), targets=[body], ephemeris=ephem, options=NOISE_FREE)
    target = result.truth.target("earth")
    assert math.degrees(target.angular_radius_rad) == pytest.approx(8.7, abs=0.05)
    image = result.signal_e
    yy, xx = np.mgrid[0 : image.shape[0], 0 : image.shape[1]]
    centroid = np.array([(image * xx).sum(), (image * yy).sum()]) / image.sum()
    assert np.all(np.abs(centroid - target.xy_cof_px) < 0.05)
    centre = np.rint(target.xy_cof_px).astype(int)
    # The disk is flat (1e5 e-/s/px * 0.1 s) and the sky far outside is dark.
    assert image[centre[1], centre[0]] == pytest.approx(1.0e4, rel=0.02)
    assert image[2, 2] < 1e-6 * 1.0e4


def test_sun_in_the_field_is_flagged_or_raises(star_catalog):
    camera = Camera.from_fov(10.0, 64, 64)
    ephem = StaticEphemeris({})
    r_obs = np.array([AU_KM, 0.0, 0.0])
    attitude = _pointing_at(-r_obs + np.array([0.0, 0.05 * AU_KM, 0.0]))
    observer = Observer(0.0, r_obs, np.zeros(3))
    flagged = render_frame(camera, attitude, observer, catalog=star_catalog, ephemeris=ephem, options=NOISE_FREE)
    assert "sun_keepout" in flagged.flags and flagged.header["OPNVFLAG"] == "sun_keepout"
    assert len(flagged.truth.stars) == 0 and flagged.signal_e.sum() == 0.0
    with pytest.raises(FrameError, match="keep-out"):
        render_frame(camera, attitude, observer, catalog=star_catalog, ephemeris=ephem,
                     options=RenderOptions(detector=DetectorOptions(noise_free=True), sun_policy="raise"))


def _nadir_uv_frame_geometry():
    """A GEO observer over the Earth (cached DE421) with a UV sensor at nadir, x along the track:
    the image axes line up with the orbit frame."""
    from opnav.ephemeris.cache import default_cached_ephemeris
    from opnav.studies import s3
    from opnav.studies.s3_images import body_attitude

    ephemeris = default_cached_ephemeris()
    t = float(parse_epoch("2001-01-01T00:10:00", "utc"))
    state = s3.geo_state()
    r_earth, v_earth = ephemeris.state("earth", t)
    observer = Observer(t, r_earth + state[:3], v_earth + state[3:])
    return ephemeris, observer, body_attitude(state), Camera.from_fov(30.0, 512, 512)


def test_limb_of_a_frame_along_the_orbit_axes_is_not_aliased():
    """The ray grid must not line up with the image axes: rays on pixel edges binned to the
    nearest pixel put the fitted limb centre of a nadir UV Earth frame 0.23 px off (it was)."""
    from opnav.image.targets import fit_limb, limb_points

    ephemeris, observer, attitude, camera = _nadir_uv_frame_geometry()
    for roll in (0.0, math.pi / 2):
        R = attitude * Rotation.from_rotvec([0.0, 0.0, roll])
        frame = render_frame(camera, R, observer, targets=("earth",), ephemeris=ephemeris,
                             options=RenderOptions(supersample=2, detector=DetectorOptions(noise_free=True)))
        truth = frame.truth.target("earth")
        fit = fit_limb(limb_points(frame.image, truth.xy_cof_px, truth.angular_radius_rad * camera.focal_length_px),
                       camera, rng=0)
        assert np.hypot(*(camera.project(fit.centre_cam) - truth.xy_cof_px)) < 0.01


def test_limb_band_render_is_the_full_render_where_the_limb_fit_reads():
    """render_windows with body_bands: the pixels within the band less the PSF's reach are those of a
    full render (noise-free, to rounding); inside the band's inner edge the disk is not drawn."""
    from opnav.render import render_windows

    ephemeris, observer, attitude, camera = _nadir_uv_frame_geometry()
    options = RenderOptions(supersample=2, detector=DetectorOptions(noise_free=True, hot_pixel_fraction=0.0))
    full = render_frame(camera, attitude, observer, targets=("earth",), ephemeris=ephemeris, options=options)
    truth = full.truth.target("earth")
    rho = truth.angular_radius_rad
    margin = (options.psf.half_width_px + 2.0) / camera.focal_length_px
    band = (rho - 10.0 / camera.focal_length_px, rho + 20.0 / camera.focal_length_px)
    windows = render_windows(camera, attitude, observer, targets=("earth",), ephemeris=ephemeris, options=options,
                             boxes=[(0, 0, camera.width_px - 1, camera.height_px - 1)], body_bands={"earth": band})
    image = windows.windows[0].image
    rows, cols = np.mgrid[:camera.height_px, :camera.width_px]
    angle = np.arccos(np.clip(attitude.apply(camera.unproject(np.column_stack([cols.ravel(), rows.ravel()])))
                              @ attitude.apply(camera.unproject(truth.xy_cof_px)), -1.0, 1.0)).reshape(camera.shape)
    read = (angle > band[0] + margin) & (angle < band[1] - margin)
    assert read.sum() > 5000
    np.testing.assert_allclose(image[read], full.image[read], rtol=1e-9)
    deep = angle < band[0] - margin
    dark = image.min()  # bias and dark current: no light
    assert np.all(image[deep] - dark < 0.01 * (full.image[deep] - dark))
    assert windows.truth.target("earth").xy_cof_px == pytest.approx(truth.xy_cof_px, abs=1e-9)


def _array_lit_rays(r_rel, half_angle, spacing, band, axes, radii, sun_from_body, shading, albedo):
    """Steps 3-4 of :mod:`opnav.bodies` with the module's array helpers (the compiled pass's reference)."""
    from opnav.bodies import _ellipsoid_hits, _ray_grid, reflectance

    rays, solid = _ray_grid(r_rel, half_angle, spacing, band)
    hit, normal_body = _ellipsoid_hits(axes.T @ (-r_rel), rays @ axes, radii)
    normal = normal_body @ axes.T
    mu, mu0 = -np.sum(rays * normal, -1), normal @ sun_from_body
    keep = hit & (mu > 0.0) & (mu0 > 0.0)
    i_over_f = np.zeros(len(rays))
    i_over_f[keep] = reflectance(mu0[keep], mu[keep], shading, albedo)
    return rays, solid, i_over_f


@pytest.mark.parametrize("shading", ["lommel-seeliger", "lambert"])
@pytest.mark.parametrize("band", [None, (0.3, 0.8)])
def test_compiled_lit_rays_equal_the_array_steps(shading, band):
    from opnav.bodies import _lit_rays

    rng = np.random.default_rng(3)
    axes = Rotation.random(random_state=4).as_matrix()
    radii = np.array([13.0, 11.4, 9.1])
    for _ in range(5):
        r_rel = rng.normal(size=3) * 4000.0
        sun = rng.normal(size=3)
        sun /= np.linalg.norm(sun)
        half = math.asin(13.0 / np.linalg.norm(r_rel))
        band_rad = None if band is None else (band[0] * half, band[1] * half)  # an annulus of the disk
        args = (r_rel, half, half / 30.0, band_rad, axes, radii, sun, shading, 0.07)
        rays, solid, i_over_f = _lit_rays(*args)
        want = _array_lit_rays(*args)
        np.testing.assert_allclose(rays, want[0], rtol=0, atol=1e-15)
        np.testing.assert_allclose(solid, want[1], rtol=1e-13)
        lit = want[2] > 0
        # a ray grazing the terminator or the limb may fall either side of a rounding
        assert np.sum((i_over_f > 0) != lit) <= 2
        both = lit & (i_over_f > 0)
        # the root of b^2 - 4ac loses digits to cancellation in either order of rounding: ~1e-9 of
        # the I/F at 300 radii, more on rays grazing the limb (where the I/F goes to 0)
        np.testing.assert_allclose(i_over_f[both], want[2][both], rtol=1e-7, atol=1e-9)
        assert both.sum() > 20  # a crescent at worst
        # what a view keeps: the flux and its first moment over the rays
        assert np.sum(i_over_f * solid) == pytest.approx(np.sum(want[2] * want[1]), rel=1e-9)
        np.testing.assert_allclose(rays.T @ (i_over_f * solid) / np.sum(i_over_f * solid),
                                   want[0].T @ (want[2] * want[1]) / np.sum(want[2] * want[1]), rtol=0, atol=1e-12)


def test_a_view_reprojected_to_a_new_attitude_and_crop_is_the_view_made_there():
    from opnav.bodies import reproject_view

    camera = Camera.from_fov(0.2, 128, 128)
    ephem, r_obs = sphere_at_phase(0.7)
    body = Body("ball", (100.0,) * 3, 0.1)
    observer = Observer(0.0, r_obs, np.zeros(3))
    R = _pointing_at(ephem.positions["ball"] - r_obs)
    turned = R * Rotation.from_rotvec([1e-4, -2e-4, 0.3])
    crop = camera.replace(width_px=40, height_px=30, cx_px=camera.cx_px - 50, cy_px=camera.cy_px - 40)
    moved = reproject_view(view_body(body, camera, R, observer, ephem, corrections=GEOMETRIC), camera, R, crop, turned)
    direct = view_body(body, crop, turned, observer, ephem, corrections=GEOMETRIC)
    np.testing.assert_allclose(moved.xy_cof_px, direct.xy_cof_px, atol=1e-9)
    np.testing.assert_allclose(moved.xy_photocentre_px, direct.xy_photocentre_px, atol=1e-9)
    np.testing.assert_allclose(moved.rays.xy_px, direct.rays.xy_px, atol=1e-9)
    light = view_body(body, crop, turned, observer, ephem, corrections=GEOMETRIC, keep_rays=False)
    assert light.rays.xy_px.shape == (0, 2)
    np.testing.assert_array_equal(light.xy_photocentre_px, direct.xy_photocentre_px)
    assert light.electrons_s == direct.electrons_s


def _light_centre(image):
    yy, xx = np.mgrid[0 : image.shape[0], 0 : image.shape[1]]
    return np.array([(image * xx).sum(), (image * yy).sum()]) / image.sum()


@pytest.mark.parametrize("shading", ["lambert", "lommel-seeliger"])
def test_a_full_sphere_s_light_is_centred_on_its_centre_at_every_pixel_phase(shading):
    """A sphere at zero phase is lit symmetrically about its line of sight, so its light's centre is
    the centre of figure (near the boresight, where the gnomonic projection keeps the symmetry to
    ~1e-5 px). Rays on a grid of their own binned to the nearest pixel put a 100 px disk's light up
    to 0.075 px off with the grid's phase against the pixels (4 rays per pixel, the body 15 px from
    the principal point); the pixels' own rays leave the sub-grid's coverage error, under 0.002 px."""
    camera = Camera.from_fov(1.0, 256, 256, exposure_s=1e-3)
    ephem, r_obs = sphere_at_phase(0.0, distance_km=1.0e5)
    radius = 0.5 * 100.0 * camera.pixel_scale_rad * 1.0e5  # 100 px across
    body = Body("ball", (radius,) * 3, 0.1, shading=shading)
    observer = Observer(0.0, r_obs, np.zeros(3))
    errors = []
    for k, (dx, dy, roll) in enumerate([(13.3, -7.6, 0.0), (-20.31, 9.22, 0.4), (30.5, 20.5, 1.1), (-7.13, -40.41, 2.0)]):
        attitude = _pointing_at(ephem.positions["ball"] - r_obs) * Rotation.from_rotvec([0.0, 0.0, roll])
        attitude = attitude * Rotation.from_rotvec([-dy / camera.focal_length_px, dx / camera.focal_length_px, 0.0])
        frame = render_frame(camera, attitude, observer, targets=[body], ephemeris=ephem, options=NOISE_FREE)
        errors.append(_light_centre(frame.signal_e) - frame.truth.target("ball").xy_cof_px)
    assert np.max(np.abs(errors)) < 0.002


def test_a_phased_ellipsoid_s_light_converges_with_the_rays_per_pixel(monkeypatch):
    """The render's own error on a phased tri-axial body: its light's centre and pixels at the default
    rays per pixel against 3 x the edge grid and 3 x the smooth one (the reference), and the total
    against the view's ray-grid flux."""
    import opnav.bodies as bodies

    camera = Camera.from_fov(1.0, 256, 256, exposure_s=1e-3)
    ephem, r_obs = sphere_at_phase(1.2, distance_km=1.0e5)
    scale = camera.pixel_scale_rad * 1.0e5  # km per px
    body = Body("ball", (40.0 * scale, 31.0 * scale, 25.0 * scale), 0.1, shading="lambert",
                pole_ra_rad=0.7, pole_dec_rad=0.3)
    attitude = _pointing_at(ephem.positions["ball"] - r_obs) * Rotation.from_rotvec([1e-5, -2e-5, 0.3])
    observer = Observer(0.0, r_obs, np.zeros(3))
    default = render_frame(camera, attitude, observer, targets=[body], ephemeris=ephem, options=NOISE_FREE)
    monkeypatch.setattr(bodies, "EDGE_SUPERSAMPLE", 3 * bodies.EDGE_SUPERSAMPLE)
    fine = render_frame(camera, attitude, observer, targets=[body], ephemeris=ephem,
                        options=RenderOptions(detector=NOISE_FREE.detector, corrections=GEOMETRIC, supersample=12))
    a, b = default.signal_e, fine.signal_e
    assert np.hypot(*(_light_centre(a) - _light_centre(b))) < 0.001
    assert np.abs(a - b).max() < 3e-3 * b.max()
    assert a.sum() == pytest.approx(default.truth.target("ball").electrons, rel=1e-3)
