"""Lost-in-space star identification on frames like those of real cameras (issue 14).

Run: ``.venv/bin/python benchmarks/starid_real.py [--frames 100] [--cameras wide,mid,s1,clip8] [--qualities 16bit,90,70,50]
[--catalog-epoch]``

Four cameras, frames rendered with :mod:`opnav.render` at random attitudes (one seeded generator per camera):

``wide``  11.4 deg, 1024 x 768 px (40"/px), 10 mm aperture, 0.5 s: the all-sky-camera class of
          the public frames in the issue (~25-35 stars extracted from the 16-bit frame).
``mid``   6.1 x 4.6 deg, 1392 x 1040 px of 6.45 um behind an 84 mm lens (15.8"/px), 0.05 s
          exposures (10-15 stars extracted a frame); 32 mm aperture, chosen so the model extracts as
          many (median ~13 at 16 bit).
``s1``    the S1 demo camera of ``opnav/data/demo.toml``: 1.0 deg, 1024 x 1024 px (3.5"/px),
          150 mm aperture, 1 s.
``clip8`` the ``mid`` optics and exposure (6.1 x 4.6 deg, 1392 x 1040 px, 0.05 s) behind an 8-bit
          read-out like that of the public tracker frames of issue 40: 11 e-/ADU and a bias of 0.8
          ADU, so the sky sits at ~1 ADU with ~0.75 ADU of noise, about a quarter of the pixels
          are clipped to exactly 0, and stars brighter than ~2,800 e- a pixel saturate at 255. Its
          frames are measured as read out (``8bit``; the ``--qualities`` apply to the other cameras).

Frames below the information limit: a frame is *scored* when at least ``MIN_DETECTABLE`` of its
rendered stars centred on the detector are above the detection limit, a matched-filter signal-to-noise ratio of
``DETECTION_SNR`` (the extractor's threshold) against the sky and read noise at the star. Fewer
stars cannot be identified: 4 make the pattern and lost-in-space asks for at least one more to
confirm it (:mod:`opnav.image.starid`, step 6). Those frames (a 6-degree field at 0.05 s, or a
1-degree field far from the Milky Way) are drawn, solved and reported on their own line (solved,
wrong, no solution); a wrong attitude there counts like any other. ``--frames`` counts scored frames.

Every frame has what real frames have: a sky background with a random linear gradient (moonlight,
twilight; up to +-60 % across the frame), vignetting (the corners receive 55-85 % of the centre's
light), a detector with ~300 hot pixels (10^3-10^5 e- each), cosmic rays, read and shot noise, and
an observer moving at 30 km/s (so the rendered stars carry ~20" of stellar aberration). Each frame
is then measured as

``16bit``  the detector's integers, and
``jpegQ``  an 8-bit frame as a consumer camera writes it: square-root stretch from 3 sigma below
           the sky to a random 40-100 sigma above it, then a JPEG round trip at quality Q (Pillow).

Each frame is solved as ``opnav solve --fov F`` does (pattern index for F +- 10 %, focal length
free within 10 %; a frame of few stars that does not solve is extracted again down to 4 sigma and solved once
more, :func:`opnav.image.starid.solve_with_deeper_extraction`, counted as "extracted again deeper"),
with extraction timed apart from identification, and with one addition every
real frame allows (its time stamp): the index's star directions are moved to the frames' epoch and
observer (proper motion and parallax, :meth:`opnav.image.starid_index.PatternIndex.at_epoch`); the
catalog's Hipparcos positions are of 1991.25 and the frames of 2024, 33 years of proper motion (up
to several arcseconds, 1-2 px of the 3.5"/px s1 camera). ``opnav solve`` does the same with the frame's date
(``--epoch`` or its FITS header); ``--catalog-epoch`` solves with the catalog-epoch directions, as
``opnav solve`` does on an undated frame. A solution is *correct* when
its apparent attitude (the solution re-fitted to the aberrated catalog directions with the known
observer velocity, :meth:`opnav.image.starid.PlateSolution.attitude`) puts the four detector corners
within 2 px of where the true attitude puts them, or when every matched star is the catalog star
rendered within 1.5 px of its centroid (the identification is right; a few-star fit whose focal
length and roll trade off can move a corner by 2-3 px: counted apart as "right stars but > 2 px");
an accepted solution that is not correct is *wrong*. Times are wall-clock medians on a shared 2-core machine.
"""

from __future__ import annotations

import argparse
import io
import math
import time
from dataclasses import dataclass

import numpy as np
from PIL import Image
from scipy.spatial.transform import Rotation

from opnav.allocator import keep_freed_memory
from opnav.camera import Camera
from opnav.catalog import load_catalog
from opnav.errors import NoSolutionError
from opnav.image.starid import solve_stars, solve_with_deeper_extraction
from opnav.image.starid_index import load_or_build_index
from opnav.observer import Observer
from opnav.render import PSF, DetectorOptions, RenderOptions, read_out, render_frame

#: Observer: 1 au from the Sun, moving at 30 km/s (ICRF, km and km/s); epoch 2024.
OBSERVER = Observer(7.57e8, np.array([1.496e8, 0.0, 0.0]), np.array([0.0, 27.5, 12.0]))
#: A scored frame has at least this many rendered stars above the detection limit (module docstring).
MIN_DETECTABLE = 5
#: Detection limit: matched-filter signal-to-noise ratio (``DetectOptions().threshold_sigma``).
DETECTION_SNR = 5.0
QUALITIES = ("16bit", "90", "70", "50")


@dataclass(frozen=True)
class Case:
    name: str
    camera: Camera
    fov_deg: float
    psf_sigma_px: float
    sky_e: float
    render_vmag: float


def cases() -> dict[str, Case]:
    from opnav.studies.s1 import load_demo

    wide = Camera.from_fov(11.4, 1024, 768, pixel_pitch_um=4.65, aperture_mm=10.0, exposure_s=0.5, read_noise_e=6.0,
                           gain_e_per_adu=1.0, full_well_e=20000.0, bit_depth=16, camera_id="wide-11.4")
    # mid: pixel pitch, scale (15.8"/px, so an 84 mm focal length), size and the 0.05 s exposure are the real
    # camera's; its aperture is not stated, so it is set from what the camera is stated to do: 10-15 stars
    # extracted a frame. With sky, PSF and noise as below, 26 mm gives a median of ~6-8 stars extracted at
    # 16 bit, 30-36 mm gives 12-15 (a sweep of 40 frames: 32 mm -> median 13, 34 mm -> 15), 40 mm and more
    # ~30; 32 mm (f/2.6) sits in the middle of the stated range.
    mid = Camera(1392, 1040, 6.45e-3 / math.radians(15.8 / 3600.0), 6.45, aperture_mm=32.0, exposure_s=0.05,
                 read_noise_e=8.0, gain_e_per_adu=1.0, full_well_e=18000.0, bit_depth=16, camera_id="mid-6.1")
    # clip8: the mid camera read out in 8 bits (module docstring); 2 e- of sky a pixel and 8 e- of read
    # noise are 0.75 ADU at 11 e-/ADU, and the bias puts the sky at ~1 ADU, so ~25 % of the pixels read 0
    clip8 = Camera(1392, 1040, mid.focal_length_mm, 6.45, aperture_mm=32.0, exposure_s=0.05, read_noise_e=8.0,
                   gain_e_per_adu=11.0, full_well_e=18000.0, bit_depth=8, bias_adu=0.8, camera_id="clip8-6.1")
    s1 = load_demo()[0].camera
    return {
        "wide": Case("wide", wide, math.degrees(wide.fov_x_rad), 1.0, 150.0, 9.5),
        "mid": Case("mid", mid, math.degrees(mid.fov_x_rad), 1.2, 20.0, 9.5),
        "s1": Case("s1", s1, math.degrees(s1.fov_x_rad), 1.0, 200.0, 14.5),
        "clip8": Case("clip8", clip8, math.degrees(clip8.fov_x_rad), 1.2, 20.0, 9.5),
    }


def render(case: Case, catalog, truth: Rotation, rng: np.random.Generator):
    """A 16-bit frame (ADU), the number of its stars above the detection limit, and its truth.

    A star's matched-filter signal-to-noise ratio for a Gaussian PSF of sigma ``s`` over a sky of
    ``b`` e-/px and read noise ``r`` is ``F / sqrt(4 pi s^2 (b + r^2))`` (F its electrons after
    vignetting; its own shot noise is negligible at the limit).
    """
    camera = case.camera
    options = RenderOptions(psf=PSF(sigma_px=case.psf_sigma_px), vmag_limit=case.render_vmag,
                            detector=DetectorOptions(noise_free=True))
    result = render_frame(camera, truth, OBSERVER, catalog=catalog, options=options)
    rows, cols = np.mgrid[0 : camera.height_px, 0 : camera.width_px].astype(float)
    u, v = (cols - camera.cx_px) / camera.width_px, (rows - camera.cy_px) / camera.height_px
    slope = rng.uniform(-0.6, 0.6, 2)
    sky = case.sky_e * camera.exposure_s / 0.5 * (1.0 + slope[0] * u + slope[1] * v)
    corner = rng.uniform(0.55, 0.85)
    vignetting = 1.0 - (1.0 - corner) * (u**2 + v**2) / 0.5
    signal = (result.signal_e + np.clip(sky, 0.0, None)) * vignetting
    hot = 300.0 / (camera.width_px * camera.height_px)
    detector = DetectorOptions(hot_pixel_fraction=hot, hot_pixel_factor=float(rng.uniform(1e3, 1e5)) / camera.exposure_s,
                               hot_pixel_seed=int(rng.integers(2**31)), cosmic_ray_rate_cm2_s=5.0)
    image = read_out(signal, camera, options=detector, rng=rng)
    stars = result.truth.stars
    # the truth also lists stars just off the frame whose light spills onto it: they cannot be centroided
    inside = camera.in_frame(stars.xy_px)
    col, row = np.rint(stars.xy_px[inside]).astype(int).T
    sky_at = np.clip(sky, 0.0, None)[row, col] * vignetting[row, col]
    snr = stars.electrons[inside] * vignetting[row, col] / np.sqrt(
        4.0 * math.pi * case.psf_sigma_px**2 * (sky_at + camera.read_noise_e**2))
    return image, int(np.sum(snr >= DETECTION_SNR)), result.truth


def to_jpeg(image: np.ndarray, quality: int, rng: np.random.Generator) -> np.ndarray:
    """Square-root stretch to 8 bits and a JPEG round trip at ``quality`` (module docstring)."""
    level = float(np.median(image))
    noise = 1.4826 * float(np.median(np.abs(image - level)))
    stretched = np.clip((image - level + 3.0 * noise) / (rng.uniform(40.0, 100.0) * noise), 0.0, 1.0) ** 0.5
    buffer = io.BytesIO()
    Image.fromarray(np.rint(255.0 * stretched).astype(np.uint8)).save(buffer, format="JPEG", quality=quality)
    return np.asarray(Image.open(io.BytesIO(buffer.getvalue())), dtype=float)


def corner_error_px(camera: Camera, R_est: Rotation, R_true: Rotation) -> float:
    corners = np.array([[0.0, 0.0], [camera.width_px - 1, 0.0], [0.0, camera.height_px - 1],
                        [camera.width_px - 1, camera.height_px - 1]])
    moved = camera.project(R_est.inv().apply(R_true.apply(camera.unproject(corners))))
    return float(np.max(np.linalg.norm(moved - corners, axis=1)))


def all_true(solution, xy: np.ndarray, frame_truth, catalog) -> bool:
    """Every matched star is the catalog star rendered within 1.5 px of its centroid."""
    ids = np.asarray(catalog.star_id)[solution.identification.pairs[:, 1]]
    rendered = dict(zip(frame_truth.stars.star_id.tolist(), frame_truth.stars.xy_px))
    return all(i in rendered and np.hypot(*(rendered[i] - xy[row])) < 1.5
               for i, row in zip(ids.tolist(), solution.identification.pairs[:, 0]))


def index_for(case: Case, catalog, *, at_epoch: bool = True):
    """The index ``opnav solve --fov`` builds for this camera (see opnav.image.starid_index), its star
    directions moved to the frames' epoch and observer unless ``at_epoch`` is False."""
    from opnav.image.starid_index import index_options_for_fov

    started = time.perf_counter()
    index = load_or_build_index(catalog, **index_options_for_fov(catalog, case.fov_deg, 0.1))
    if at_epoch:
        index = index.at_epoch(catalog, t_tdb_s=OBSERVER.t_tdb_s, r_observer_ssb_km=OBSERVER.r_ssb_km)
    print(f"  index for {case.fov_deg:.2f} deg: {len(index.patterns)} patterns, {len(index.star_vectors)} stars, "
          f"V <= {index.options.vmag_limit:.2f}, star directions at the {'frame' if at_epoch else 'catalog'} epoch, "
          f"load/build {time.perf_counter() - started:.1f} s")
    return index


def run_case(case: Case, catalog, frames: int, qualities, rng: np.random.Generator, *, at_epoch: bool = True
             ) -> list[str]:
    camera = case.camera
    if camera.bit_depth == 8:
        qualities = ("8bit",)  # the 8-bit read-out as it is (module docstring)
    print(f"[{case.name}] {case.fov_deg:.2f} x {math.degrees(camera.fov_y_rad):.2f} deg, {camera.width_px} x "
          f"{camera.height_px} px, {3600 * math.degrees(camera.pixel_scale_rad):.1f}\"/px, exposure {camera.exposure_s} s")
    index = index_for(case, catalog, at_epoch=at_epoch)
    stats = {q: {"ok": 0, "wrong": 0, "coarse": 0, "fail": 0, "deeper": 0, "extract": [], "solve": [], "stars": []} for q in qualities}
    # frames below the information limit: solved all the same, tallied apart
    limited = {q: {"ok": 0, "wrong": 0, "fail": 0} for q in qualities}
    n_limited = 0
    scored = 0
    while scored < frames:
        truth = Rotation.random(random_state=rng.integers(2**31))
        image16, n_detectable, frame_truth = render(case, catalog, truth, rng)
        below = n_detectable < MIN_DETECTABLE
        if below:
            n_limited += 1
        else:
            scored += 1
        for quality in qualities:
            lossy = quality not in ("16bit", "8bit")
            image = to_jpeg(image16, int(quality), rng) if lossy else image16.astype(float)
            saturation = 255.0 if lossy else float(2**camera.bit_depth - 1)
            solve_times, stars_used = [], []

            def solve(xy, cov):
                stars_used.append(xy)
                started = time.perf_counter()
                try:
                    return solve_stars(xy, cov, image.shape, index=index, fov_deg=case.fov_deg, fov_tolerance=0.1)
                finally:
                    solve_times.append(time.perf_counter() - started)

            started = time.perf_counter()
            try:
                solution = solve_with_deeper_extraction(image, solve, saturation_adu=saturation, lossy=lossy)
            except NoSolutionError:
                solution = None
            elapsed = time.perf_counter() - started
            xy = stars_used[-1]
            if below:
                tally = limited[quality]
                if solution is None:
                    tally["fail"] += 1
                elif corner_error_px(camera, solution.attitude(v_observer_km_s=OBSERVER.v_ssb_km_s), truth) < 2.0 \
                        or all_true(solution, xy, frame_truth, catalog):
                    tally["ok"] += 1
                else:
                    tally["wrong"] += 1
                    print(f"  WRONG {case.name} {quality} frame below the limit ({n_detectable} stars detectable)")
                continue
            record = stats[quality]
            record["extract"].append(elapsed - sum(solve_times))
            record["solve"].append(sum(solve_times))
            record["stars"].append(len(stars_used[0]))
            record["deeper"] += len(stars_used) > 1
            if solution is None:
                record["fail"] += 1
            else:
                error_px = corner_error_px(camera, solution.attitude(v_observer_km_s=OBSERVER.v_ssb_km_s), truth)
                if error_px < 2.0:
                    record["ok"] += 1
                elif all_true(solution, xy, frame_truth, catalog):
                    record["ok"] += 1
                    record["coarse"] += 1
                else:
                    record["wrong"] += 1
                    ident = solution.identification
                    print(f"  WRONG {case.name} {quality} frame {scored}: corner error {error_px:.1f} px, "
                          f"{len(ident.pairs)} matched of {len(xy)}, p_false {ident.p_false:.2g}, "
                          f"focal scale {ident.focal_scale:.4f}, residuals max {np.degrees(ident.residuals_rad.max()) * 3600:.1f}\"")
    lines = []
    for quality in qualities:
        r = stats[quality]
        label = quality.replace("bit", "-bit") if quality.endswith("bit") else f"JPEG q{quality}"
        line = (f"  {case.name:4s} {label:8s}: solved {r['ok']}/{frames} = {100.0 * r['ok'] / frames:6.2f} %, wrong {r['wrong']}, "
                f"no solution {r['fail']} (right stars but > 2 px: {r['coarse']}); stars extracted median {np.median(r['stars']):.0f}, "
                f"extracted again deeper {r['deeper']}; "
                f"extract median {1e3 * np.median(r['extract']):.1f} ms (95 % {1e3 * np.percentile(r['extract'], 95):.1f}), "
                f"solve median {1e3 * np.median(r['solve']):.2f} ms (95 % {1e3 * np.percentile(r['solve'], 95):.1f})")
        print(line, flush=True)
        lines.append(line)
    if n_limited:
        for quality in qualities:
            t = limited[quality]
            label = quality.replace("bit", "-bit") if quality.endswith("bit") else f"JPEG q{quality}"
            line = (f"  {case.name:4s} {label:8s}: below the information limit (< {MIN_DETECTABLE} stars at matched-filter "
                    f"SNR >= {DETECTION_SNR:g}), not scored: {n_limited} frames, solved {t['ok']}, wrong {t['wrong']}, "
                    f"no solution {t['fail']}")
            print(line, flush=True)
            lines.append(line)
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=100, help="scored frames per camera (default 100)")
    parser.add_argument("--cameras", default="wide,mid,s1,clip8", help="comma-separated subset of wide, mid, s1, clip8")
    parser.add_argument("--qualities", default=",".join(QUALITIES),
                        help="comma-separated subset of 16bit, 90, 70, 50 (clip8 frames are measured as read out)")
    parser.add_argument("--seed", type=int, default=14)
    parser.add_argument("--catalog-epoch", action="store_true",
                        help="solve with the catalog-epoch star directions, as opnav solve does on an undated frame")
    parser.add_argument("--malloc-defaults", action="store_true",
                        help="leave the C allocator's defaults (the opnav command keeps freed memory: "
                             "opnav.allocator.keep_freed_memory)")
    args = parser.parse_args()
    if not args.malloc_defaults:
        keep_freed_memory()
    catalog = load_catalog()
    all_cases = cases()
    summary = []
    for name in args.cameras.split(","):
        # one generator per camera: a camera's frames do not depend on which others run
        rng = np.random.default_rng([args.seed, list(all_cases).index(name)])
        summary += run_case(all_cases[name], catalog, args.frames, args.qualities.split(","), rng,
                            at_epoch=not args.catalog_epoch)
    print("summary:")
    print("\n".join(summary))


if __name__ == "__main__":
    main()
