"""Cross-correlation centres (issues 37/38): bias, scatter and covariance consistency of
:func:`opnav.image.correlate.correlate_centre` (ellipsoids) and
:func:`opnav.image.mesh_centre.correlate_mesh_centre` (the shipped mesh) on rendered frames.

Frames: the tests' scene builder (``tests/image/centre_scene.py``: a 1024 x 1024 px camera at
20"/px, the Sun 1.5 au away, the body placed off the principal point) of Mars, the Moon, Phobos and
opnav's shipped mesh (``asteroid``: 5,120 facets, Lommel-Seeliger, spinning about a tilted pole),
``--sizes`` px across (largest axis) at ``--phases`` deg, a Gaussian PSF (``--psf``), the brightest
pixel near ``--peak-e`` electrons, read out with shot and read noise, cosmic rays and hot pixels
(opnav's detector model; ``--clean`` without the last two). The frames are drawn with
``--frame-supersample`` rays per pixel per axis where the shading is smooth (the image loop of
``opnav run --mode images`` draws with 2; the templates use 2 for ellipsoids, 4 for meshes).
The frames come from the same renderer as the templates, so its pixel-phase error (the light's
centre moving with the body's place within its pixels: up to 0.1 px on a 5 px crescent) is in
both and mostly cancels once the template is drawn where the frame's body is; ``--fine N`` draws
each frame on a camera N times finer (its PSF set so the blur's variance is the coarse frame's)
and sums its pixels N x N, so the frame's error is the renderer's at a 1/N-scale pixel phase, not
the template's: what a real frame does to the centre.
Each seed draws new noise and a new a-priori pose: the centre ``--prior-px`` px (1 sigma per axis)
and the range ``--prior-range`` (1 sigma, relative) off the truth.

Printed per case: bias (mean error, px) with its standard error, scatter (px, the larger axis),
reported sigma (px, the larger axis's RMS), their ratio, chi-square per dof of the errors against
the reported covariances about the truth (bias included), ``whitened``: the scatter over the sigma
with each frame whitened by its own covariance about the case's mean (both axes pooled) and the
range its 2 (n - 1) dof allow at 99 %, the fit's own chi-square per dof, and the median CPU time
of the whole centre finding (templates included, ``time.process_time``).

Run: ``nice -n 10 .venv/bin/python benchmarks/correlation_centre.py`` (a few minutes).
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "image"))
import centre_finding  # noqa: E402  (this folder's: the per-case summary, one copy)
import centre_scene  # noqa: E402  (the tests' scene builder: one copy)

from opnav.bodies import Body  # noqa: E402
from opnav.errors import NoSolutionError  # noqa: E402
from opnav.image.centres import body_pose  # noqa: E402
from opnav.image.correlate import DetectorNoise, correlate_centre  # noqa: E402
from opnav.image.mesh_centre import correlate_mesh_centre, mesh_pose  # noqa: E402
from opnav.render.detector import DetectorOptions, read_out  # noqa: E402
from opnav.shape import read_obj, shipped_shape  # noqa: E402

MESH = read_obj(shipped_shape())
# the shipped mesh as the scene builder's fourth body: its reflectance and spin as in samples/asteroid_approach.toml
centre_scene.BODIES.setdefault("asteroid", Body("asteroid", MESH.half_extents_km(), 0.15, shading="lommel-seeliger",
                                                shape=MESH, pole_ra_rad=math.radians(57.3),
                                                pole_dec_rad=math.radians(34.4),
                                                rotation_rate_rad_s=2.0 * math.pi / (7.3 * 3600.0)))
CLEAN = DetectorOptions(hot_pixel_fraction=0.0, cosmic_ray_rate_cm2_s=0.0)


def _prior(pose, camera, rng, prior_px: float, prior_range: float):
    """The a-priori pose: the truth turned by ``prior_px`` px per axis and its range scaled."""
    f = camera.focal_length_px
    turn = Rotation.from_rotvec([rng.normal(0, prior_px) / f, rng.normal(0, prior_px) / f, 0.0])
    return pose.at(turn.apply(pose.r_cam_km) * (1.0 + rng.normal(0, prior_range)))


def run_case(name: str, diameter: float, phase: float, *, seeds: int, rng, args) -> dict:
    """``seeds`` noise draws and priors of one body, size and phase: errors (n, 2) px, covariances
    (n, 2, 2) px^2, the fits' chi-square per dof, CPU seconds, failures."""
    n = args.fine
    coarse = centre_scene.camera_1mp()
    # a camera n times finer on the same field: its pixel (i, j) is within the coarse pixel (i // n, j // n)
    fine = replace(coarse, width_px=n * coarse.width_px, height_px=n * coarse.height_px,
                   pixel_pitch_um=coarse.pixel_pitch_um / n, cx_px=None, cy_px=None)
    # the fine frame's blur (PSF, its pixels' boxes, the n x n sum) the same variance as the coarse one's
    psf_fine = n * math.sqrt(args.psf**2 + 1.0 / 6.0 - (n * n + 1.0) / (12.0 * n * n))
    mesh = name == "asteroid"
    pose_of = mesh_pose if mesh else body_pose

    def frame(offset_px):
        """The noise-free signal (e-) of the body ``offset_px`` from the principal point, its camera, the
        truth's pose and centre (px)."""
        scene = centre_scene.render_scene(name, n * diameter, phase, rng=None, noise=False, psf_sigma_px=psf_fine,
                                          supersample=args.frame_supersample, peak_e=args.peak_e / (n * n),
                                          camera=fine, offset_px=tuple(n * np.asarray(offset_px)))
        cam = replace(coarse, exposure_s=scene.camera.exposure_s)
        signal = scene.signal_e.reshape(cam.height_px, n, cam.width_px, n).sum(axis=(1, 3))
        truth_pose = pose_of(scene.body, scene.R_icrf_cam, scene.observer, scene.ephemeris)
        xy_true = cam.project(truth_pose.r_cam_km)
        if n == 1 and np.hypot(*(xy_true - scene.xy_true_px)) > 1e-6:
            raise RuntimeError(f"the pose's centre {xy_true} is not the renderer's {scene.xy_true_px}")
        return signal, cam, truth_pose, xy_true

    noise = DetectorNoise(coarse.read_noise_e, coarse.gain_e_per_adu, coarse.bias_adu)
    detector = CLEAN if args.clean else DetectorOptions()
    errs, covs, fit_chi2, cpu, fails = [], [], [], [], 0
    if not args.move:
        signal, cam, truth_pose, xy_true = frame((13.3, -7.6))
    for _ in range(seeds):
        if args.move:
            # each frame's body at its own place within its pixels (a renderer's pixel-phase error is
            # then a scatter over the frames, as on a mission, not one bias of the case)
            signal, cam, truth_pose, xy_true = frame((13.3, -7.6) + rng.uniform(0.0, 1.0, 2))
        image = np.asarray(read_out(signal, cam, options=detector, rng=rng), float)
        prior = _prior(truth_pose, cam, rng, args.prior_px, args.prior_range)
        c0 = time.process_time()
        try:
            if mesh:
                fit = correlate_mesh_centre(image, cam, prior, psf_sigma_px=args.psf, noise=noise)
            else:
                fit = correlate_centre(image, cam, prior, psf_sigma_px=args.psf, noise=noise)
        except NoSolutionError:
            fails += 1
            continue
        cpu.append(time.process_time() - c0)
        errs.append(fit.xy_px - xy_true)
        covs.append(fit.cov_xy_px2)
        fit_chi2.append(fit.chi2 / fit.dof)
    return dict(name=name, diameter=diameter, phase=phase, errs=np.array(errs).reshape(-1, 2),
                covs=np.array(covs).reshape(-1, 2, 2), fit_chi2=np.array(fit_chi2), cpu=np.array(cpu), fails=fails)


def summarise(case: dict) -> dict | None:
    """:func:`centre_finding.summarise` (bias, scatter, sigma, chi-square per dof about the truth, the
    whitened scatter about the case's mean with its 99 % range) of a case of at least 3 frames, its
    ``ratio`` the larger axis's scatter over the larger axis's sigma (module notes)."""
    if len(case["errs"]) < 3:
        return None
    s = centre_finding.summarise(case)
    return {**s, "ratio": float(max(s["scatter"]) / max(s["sigma"]))}


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--bodies", default="phobos,moon,asteroid", help="comma-separated: mars, moon, phobos, asteroid")
    p.add_argument("--sizes", default="5,10,20,40", help="apparent diameters, px (comma-separated)")
    p.add_argument("--phases", default="0,30,60,90,120", help="phase angles, deg (comma-separated)")
    p.add_argument("--seeds", type=int, default=16, help="noise draws (and priors) per case")
    p.add_argument("--psf", type=float, default=1.2, help="Gaussian PSF sigma, px")
    p.add_argument("--peak-e", type=float, default=20000.0, help="electrons in the brightest pixel")
    p.add_argument("--frame-supersample", type=int, default=4,
                   help="the frames' rays per pixel per axis where the shading is smooth (edges get 32)")
    p.add_argument("--prior-px", type=float, default=1.0)
    p.add_argument("--prior-range", type=float, default=0.01)
    p.add_argument("--fine", type=int, default=1,
                   help="draw each frame on a camera this many times finer and sum its pixels n x n (the frame's "
                        "pixel-phase errors then not the template's)")
    p.add_argument("--move", action=argparse.BooleanOptionalAction, default=True,
                   help="draw each seed's frame with the body at a new place within its pixels (default)")
    p.add_argument("--clean", action="store_true", help="no cosmic rays or hot pixels")
    p.add_argument("--seed", type=int, default=37)
    args = p.parse_args(argv)
    rng = np.random.default_rng(args.seed)
    bodies = [b.strip() for b in args.bodies.split(",") if b.strip()]
    unknown = [b for b in bodies if b not in centre_scene.BODIES]
    if unknown:
        p.error(f"--bodies: unknown {', '.join(unknown)}; accepted: {', '.join(centre_scene.BODIES)}")
    sizes = [float(s) for s in args.sizes.split(",")]
    phases = [float(s) for s in args.phases.split(",")]
    finer = f", frames drawn {args.fine}x finer and summed" if args.fine > 1 else ""
    print(f"correlation centres: {args.seeds} seeds a case, PSF sigma {args.psf} px, peak {args.peak_e:g} e-, prior "
          f"{args.prior_px} px and {100 * args.prior_range:.1f} % range, frames at supersample {args.frame_supersample}"
          f"{', clean detector' if args.clean else ''}{finer}")
    print(f"{'body':8s} {'D px':>5s} {'ph':>4s} {'n':>3s} {'bias x':>8s} {'bias y':>8s} {'+-se':>7s} {'scat':>7s} "
          f"{'sigma':>7s} {'sc/sg':>5s} {'chi2/dof':>8s} {'white':>5s} {'99% range':>11s} {'fit x2':>6s} "
          f"{'ms cpu':>6s}")
    rows = []
    for name in bodies:
        for diameter in sizes:
            for phase in phases:
                case = run_case(name, diameter, phase, seeds=args.seeds, rng=rng, args=args)
                s = summarise(case)
                rows.append((case, s))
                if s is None:
                    print(f"{name:8s} {diameter:5g} {phase:4g} fails {case['fails']}", flush=True)
                    continue
                print(f"{name:8s} {diameter:5g} {phase:4g} {s['n']:3d} {s['bias'][0]:8.4f} {s['bias'][1]:8.4f} "
                      f"{max(s['bias_se']):7.4f} {max(s['scatter']):7.4f} {max(s['sigma']):7.4f} {s['ratio']:5.2f} "
                      f"{s['chi2_dof']:8.2f} {s['whitened']:5.2f} {s['whitened_lo']:5.2f}-{s['whitened_hi']:<5.2f} "
                      f"{case['fit_chi2'].mean():6.2f} {1e3 * np.median(case['cpu']):6.1f}"
                      + (f"  ({case['fails']} failed)" if case["fails"] else ""), flush=True)
    done = [(c, s) for c, s in rows if s]
    if not done:
        return
    outside = [(c, s) for c, s in done if s["whitened_hi"] < 0.8 or s["whitened_lo"] > 1.2]
    dof = sum(2 * (s["n"] - 1) for _, s in done)
    pooled = math.sqrt(sum(s["chi2_mean_sum"] for _, s in done) / dof)
    chi2_truth = sum(s["chi2_dof"] * s["n"] for _, s in done) / sum(s["n"] for _, s in done)
    inside = sum(0.8 <= s["whitened"] <= 1.2 for _, s in done)
    print(f"\n{len(done)} cases: whitened scatter / sigma {min(s['whitened'] for _, s in done):.2f} .. "
          f"{max(s['whitened'] for _, s in done):.2f}, pooled {pooled:.3f}; {inside} inside 0.8 .. 1.2; "
          f"chi-square per dof about the truth, pooled {chi2_truth:.3f}; cases whose 99 % range "
          f"misses 0.8 .. 1.2: {len(outside)}"
          + "".join(f"\n    {c['name']} {c['diameter']:g} px {c['phase']:g} deg: {s['whitened']:.2f} "
                    f"({s['whitened_lo']:.2f} .. {s['whitened_hi']:.2f})" for c, s in outside))
    print(f"  CPU per centre, worst case's median: {1e3 * max(np.median(c['cpu']) for c, _ in done):.1f} ms "
          "(templates included)")


if __name__ == "__main__":
    main()
