"""Centre finding for resolved bodies (issue 37 item 2): bias, scatter and covariance consistency of
the limb-based ellipsoid fit and of template cross-correlation on rendered frames.

Frames: opnav's renderer (``render_frame``, ``supersample`` rays per pixel per axis) of Mars and
the Moon (ellipsoids: Lambert and Lommel-Seeliger) and Phobos (tri-axial, synchronous), 5-800 px
across, phase 0-120 deg, a 1024 x 1024 px camera, Gaussian PSF blur (``--psf``), shot and read noise
with cosmic rays and hot pixels (opnav's detector model), the brightest pixel near 20,000 e-.
Each seed draws new noise and a new a-priori pose: the centre ``--prior-px`` px (1 sigma per
axis) and the range ``--prior-range`` (1 sigma, relative) off the truth. The method is the one
:func:`opnav.image.centres.choose_method` picks (by size and phase), or ``--method``.

Printed per case: bias (mean error, px) of the centre with its standard error, scatter (px),
mean reported sigma (px), scatter / sigma, chi-square per dof of the centre errors against the
reported covariances, range bias and scatter (% of range; limb only), times per frame (ms): the
whole centre finding (model images included) in wall-clock and CPU time (``time.process_time``:
on a shared machine the wall clock counts other jobs' turns), and the fit alone (one pass, model
given, the final pass's fit to the lines' response) in CPU time, and ``white``: the scatter over
the sigma with each frame whitened by its own covariance about the case's mean, both axes pooled.
Then the acceptance lines of issue 37 on the limb cases >= 20 px at phase <= 90 deg; the pooled
chi-square is given about the truth (bias included) and about each case's mean (the noise alone:
does the covariance describe the scatter); per case, ``white`` with the range its 2 (n - 1) dof
allow at 99 % (chi-square), a case counted outside 0.8 .. 1.2 only when that range misses it (8
seeds give a ratio to ~27 %: ``--seeds 50`` to ~10 %).

Truth: the renderer's own centre of figure and light-time range. The renderer integrates each
pixel on its own rays (:func:`opnav.bodies.body_pixels`: ``supersample`` per axis where the shading
is smooth, 32 where the limb or the terminator crosses a pixel), so the light it draws is the
body's to under 0.001 px (a phased 80 px body's light centre against a render three times finer,
``tests/render/test_render_bodies.py``); before, its own ray grid binned to the nearest pixel put
a 100 px disk's light up to 0.1 px off its centre.

Basilisk (``--basilisk PYTHON``: a Python with ``pip install bsk bsk-opnav``, run in a subprocess):
its Hough circle finder (``houghCircles``) and limb finder (``limbFinding``) on the same noisy
frames of Mars, written as the 8-bit PNG files they read (the frame minus bias scaled so its
brightest pixel is 255), with the Hough radius bounds set to 0.5-1.5 times the true radius and the
modules' other thresholds at their defaults. Basilisk's limb points (whole edge pixels, terminator
included) are reduced to a centre by a least-squares circle fit (its ``horizonOpNav`` needs the
camera and attitude messages; for a sphere near the boresight a circle in pixels is the same fit).

Run: ``.venv/bin/python benchmarks/centre_finding.py`` (a few minutes); ``--full`` the whole grid.
"""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation
from scipy.stats import chi2 as chi2_dist

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "image"))
from centre_scene import render_scene  # noqa: E402  (the tests' scene builder: one copy)

from opnav.errors import NoSolutionError  # noqa: E402
from opnav.image.centres import CentreOptions, apparent_diameter_px, body_pose, choose_method  # noqa: E402
from opnav.image.correlate import correlate_centre  # noqa: E402
from opnav.image.limb import DetectorNoise, fit_limb_ellipsoid, fit_outline, limb_offsets, scan_lines  # noqa: E402
from opnav.render.detector import DetectorOptions, read_out  # noqa: E402

QUICK = {
    "mars": ((20, 50, 100, 300, 800), (0, 30, 60, 90, 120)),
    "moon": ((10, 20, 100, 400), (0, 45, 90, 120)),
    "phobos": ((5, 10, 20, 40, 80), (0, 30, 60, 90, 120)),
}
FULL = {
    "mars": ((5, 10, 20, 50, 100, 200, 400, 800), (0, 30, 60, 90, 120)),
    "moon": ((5, 10, 20, 50, 100, 200, 400, 800), (0, 30, 60, 90, 120)),
    "phobos": ((5, 10, 20, 40, 80, 160), (0, 30, 60, 90, 120)),
}


def _prior(pose, camera, rng, prior_px: float, prior_range: float):
    """The a-priori pose: the truth turned by ``prior_px`` px per axis and its range scaled."""
    f = camera.focal_length_px
    turn = Rotation.from_rotvec([rng.normal(0, prior_px) / f, rng.normal(0, prior_px) / f, 0.0])
    return pose.at(turn.apply(pose.r_cam_km) * (1.0 + rng.normal(0, prior_range)))


def run_case(name, diameter, phase, *, seeds, rng, args):
    scene = render_scene(name, diameter, phase, rng=None, noise=False, psf_sigma_px=args.psf,
                         supersample=args.supersample)
    cam = scene.camera
    signal = scene.signal_e  # the light before the detector: each seed reads it out anew
    truth_pose = body_pose(scene.body, scene.R_icrf_cam, scene.observer, scene.ephemeris)
    method = choose_method(apparent_diameter_px(cam, truth_pose), truth_pose.phase_rad,
                           options=CentreOptions(method=args.method))
    noise = DetectorNoise(cam.read_noise_e, cam.gain_e_per_adu, cam.bias_adu)
    errs, covs, range_err, range_sig, t_all, t_fit, fails, frames = [], [], [], [], [], [], 0, []
    radius_px = 0.5 * apparent_diameter_px(cam, truth_pose)
    for _ in range(seeds):
        image = np.asarray(read_out(signal, cam, options=DetectorOptions(), rng=rng), float)
        if args.basilisk and name == "mars":
            frames.append((image, cam.bias_adu, radius_px, scene.xy_true_px))
        prior = _prior(truth_pose, cam, rng, args.prior_px, args.prior_range)
        try:
            t0, c0 = time.perf_counter(), time.process_time()
            if method == "limb":
                fit = fit_limb_ellipsoid(image, cam, prior, psf_sigma_px=args.psf, noise=noise)
                t_all.append((time.perf_counter() - t0, time.process_time() - c0))
                scan = scan_lines(cam, prior.at(fit.r_cam_km), psf_sigma_px=args.psf)
                t1, c1 = time.perf_counter(), time.process_time()
                fit_outline(scan, limb_offsets(image, scan, noise), cam, linear=True)
                t_fit.append((time.perf_counter() - t1, time.process_time() - c1))
                range_err.append(fit.range_km / scene.range_true_km - 1.0)
                range_sig.append(fit.sigma_range_km / scene.range_true_km)
            else:
                fit = correlate_centre(image, cam, prior, psf_sigma_px=args.psf, noise=noise)
                t_all.append((time.perf_counter() - t0, time.process_time() - c0))
                t_fit.append((np.nan, np.nan))
        except NoSolutionError:
            fails += 1
            continue
        errs.append(fit.xy_px - scene.xy_true_px)
        covs.append(fit.cov_xy_px2)
    return dict(name=name, diameter=diameter, phase=phase, method=method, errs=np.array(errs).reshape(-1, 2),
                covs=np.array(covs).reshape(-1, 2, 2), range_err=np.array(range_err), range_sig=np.array(range_sig),
                t_all=np.array(t_all).reshape(-1, 2), t_fit=np.array(t_fit).reshape(-1, 2), fails=fails, frames=frames)


BASILISK_WORKER = """
import json, sys
import numpy as np
from Basilisk.utilities import SimulationBaseClass, macros
from Basilisk.fswAlgorithms import houghCircles, limbFinding
from Basilisk.architecture import messaging
out = []
for path, radius in json.load(open(sys.argv[1])):
    sim = SimulationBaseClass.SimBaseClass()
    proc = sim.CreateNewProcess("p")
    proc.addTask(sim.CreateNewTask("t", macros.sec2nano(0.5)))
    hough = houghCircles.HoughCircles(); hough.ModelTag = "hough"
    limb = limbFinding.LimbFinding(); limb.ModelTag = "limb"
    for m in (hough, limb):
        sim.AddModelToTask("t", m)
        m.filename = path
    hough.expectedCircles = 1
    hough.houghMinRadius = int(0.5 * radius)
    hough.houghMaxRadius = int(1.5 * radius) + 2
    hough.houghMinDist = int(max(radius, 10))
    msg = messaging.CameraImageMsgPayload(); msg.timeTag = 1; msg.valid = 1; msg.cameraID = 1
    img = messaging.CameraImageMsg().write(msg)
    hough.imageInMsg.subscribeTo(img); limb.imageInMsg.subscribeTo(img)
    lh = hough.opnavCirclesOutMsg.recorder(); ll = limb.opnavLimbOutMsg.recorder()
    sim.AddModelToTask("t", lh); sim.AddModelToTask("t", ll)
    sim.InitializeSimulation(); sim.ConfigureStopTime(macros.sec2nano(0.5)); sim.ExecuteSimulation()
    n = int(np.array(ll.numLimbPoints)[-1])
    out.append({"hough_valid": int(np.array(lh.valid)[-1]), "hough": np.array(lh.circlesCenters)[-1][:2].tolist(),
                "hough_radius": float(np.array(lh.circlesRadii)[-1][0]),
                "limb": np.array(ll.limbPoints)[-1][:2 * n].reshape(-1, 2).tolist()})
json.dump(out, open(sys.argv[2], "w"))
"""


def circle_fit(points: np.ndarray) -> np.ndarray | None:
    """Centre (2,) of the least-squares circle through ``points`` (N, 2): algebraic (Kasa) start,
    then Gauss-Newton on the geometric distances."""
    if len(points) < 5:
        return None
    x, y = points.T
    a = np.column_stack([x, y, np.ones_like(x)])
    sol, *_ = np.linalg.lstsq(a, x * x + y * y, rcond=None)
    c = sol[:2] / 2.0
    r = math.sqrt(max(sol[2] + c @ c, 0.0))
    for _ in range(20):
        d = points - c
        rho = np.hypot(*d.T)
        jac = np.column_stack([-d / rho[:, None], -np.ones_like(rho)])
        step, *_ = np.linalg.lstsq(jac, -(rho - r), rcond=None)
        c, r = c + step[:2], r + step[2]
        if np.max(np.abs(step)) < 1e-10:
            break
    return c


def basilisk_side(python, frames):
    """Basilisk's Hough and limb centres on ``frames`` [(image, bias, radius_px, truth_xy)]: per frame
    (hough error (2,) or None, limb circle-fit error (2,) or None, limb points)."""
    import cv2

    with tempfile.TemporaryDirectory() as tmp:
        jobs = []
        for k, (image, bias, radius, _) in enumerate(frames):
            scaled = np.clip((image - bias) / max(float((image - bias).max()), 1.0) * 255.0, 0, 255)
            path = f"{tmp}/f{k:04d}.png"
            cv2.imwrite(path, np.rint(scaled).astype(np.uint8))
            jobs.append((path, float(radius)))
        Path(tmp, "jobs.json").write_text(json.dumps(jobs))
        Path(tmp, "worker.py").write_text(BASILISK_WORKER)
        done = subprocess.run([python, f"{tmp}/worker.py", f"{tmp}/jobs.json", f"{tmp}/out.json"],
                              capture_output=True, text=True, timeout=3600)
        if done.returncode != 0:
            raise RuntimeError(f"Basilisk worker failed: {done.stderr.strip().splitlines()[-1:]}")
        results = json.loads(Path(tmp, "out.json").read_text())
    out = []
    for (_, _, _, truth), res in zip(frames, results):
        hough = np.array(res["hough"]) - truth if res["hough_valid"] and res["hough_radius"] > 0 else None
        pts = np.array(res["limb"], float).reshape(-1, 2)
        centre = circle_fit(pts)
        out.append((hough, None if centre is None else centre - truth, len(pts)))
    return out


def summarise(case):
    e, c = case["errs"], case["covs"]
    n = len(e)
    if n < 2:
        return None
    bias = e.mean(0)
    scatter = e.std(0, ddof=1)
    sigma = np.sqrt(np.mean(c[:, [0, 1], [0, 1]], 0))
    chi2 = np.array([ei @ np.linalg.solve(ci, ei) for ei, ci in zip(e, c)])
    # about the case's mean: the noise alone (the renderer's truth and the method's bias taken out)
    chi2_mean = np.array([(ei - bias) @ np.linalg.solve(ci, ei - bias) for ei, ci in zip(e, c)])
    # the case's own scatter over its reported covariance, both axes pooled, each frame whitened by
    # its own covariance (about the case's mean), and the range of ratios the case's 2 (n - 1) dof
    # allow at 99 %: the ratio is outside 0.8 .. 1.2 only when this range misses it
    dof = 2 * (n - 1)
    whitened = math.sqrt(float(chi2_mean.sum()) / dof)
    lo, hi = (float(whitened / math.sqrt(q / dof)) for q in chi2_dist.ppf([0.995, 0.005], dof))
    return dict(n=n, bias=bias, bias_se=scatter / math.sqrt(n), scatter=scatter, sigma=sigma,
                ratio=scatter / sigma, chi2_dof=float(chi2.mean() / 2.0), chi2_sum=float(chi2.sum()),
                chi2_mean_sum=float(chi2_mean.sum()), whitened=whitened, whitened_lo=lo, whitened_hi=hi)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seeds", type=int, default=8, help="noise draws (and priors) per case")
    p.add_argument("--full", action="store_true", help="the whole grid of sizes and phases")
    p.add_argument("--method", default="auto", choices=("auto", "limb", "correlation"))
    p.add_argument("--psf", type=float, default=1.2, help="Gaussian PSF sigma, px")
    p.add_argument("--supersample", type=int, default=4,
                   help="renderer rays per pixel per axis where the shading is smooth (edges get 32)")
    p.add_argument("--prior-px", type=float, default=1.0)
    p.add_argument("--prior-range", type=float, default=0.01)
    p.add_argument("--seed", type=int, default=37)
    p.add_argument("--basilisk", metavar="PYTHON", default=None,
                   help="a Python with bsk and bsk-opnav: Basilisk's Hough and limb finders on the Mars frames")
    args = p.parse_args(argv)
    rng = np.random.default_rng(args.seed)
    grid = FULL if args.full else QUICK
    print(f"centre finding: {args.seeds} seeds a case, PSF sigma {args.psf} px, prior {args.prior_px} px and "
          f"{100 * args.prior_range:.1f} % range, renderer supersample {args.supersample}")
    header = (f"{'body':7s} {'D px':>5s} {'ph':>4s} {'method':11s} {'n':>3s} {'bias x':>8s} {'bias y':>8s} "
              f"{'+-se':>7s} {'scat':>7s} {'sigma':>7s} {'sc/sg':>5s} {'chi2/dof':>8s} {'rng bias%':>9s} "
              f"{'rng sc%':>8s} {'rng sg%':>8s} {'ms wall':>7s} {'ms cpu':>7s} {'fit cpu':>7s} {'white':>5s}")
    print(header)
    cases = []
    for name, (sizes, phases) in grid.items():
        for diameter in sizes:
            for phase in phases:
                case = run_case(name, diameter, phase, seeds=args.seeds, rng=rng, args=args)
                s = summarise(case)
                cases.append((case, s))
                if s is None:
                    print(f"{name:7s} {diameter:5d} {phase:4d} {case['method']:11s} fails {case['fails']}")
                    continue
                rb = (f"{100 * case['range_err'].mean():9.4f} {100 * case['range_err'].std(ddof=1):8.4f} "
                      f"{100 * case['range_sig'].mean():8.4f}" if case["range_err"].size > 1 else f"{'':9s} {'':8s} {'':8s}")
                t_fit = (f"{1e3 * np.nanmedian(case['t_fit'][:, 1]):7.1f}" if np.isfinite(case['t_fit']).any()
                         else f"{'':7s}")
                print(f"{name:7s} {diameter:5d} {phase:4d} {case['method']:11s} {s['n']:3d} {s['bias'][0]:8.4f} "
                      f"{s['bias'][1]:8.4f} {max(s['bias_se']):7.4f} {max(s['scatter']):7.4f} {max(s['sigma']):7.4f} "
                      f"{max(s['ratio']):5.2f} {s['chi2_dof']:8.2f} {rb} {1e3 * np.median(case['t_all'][:, 0]):7.1f} "
                      f"{1e3 * np.median(case['t_all'][:, 1]):7.1f} {t_fit} {s['whitened']:5.2f}"
                      + (f"  ({case['fails']} failed)" if case["fails"] else ""), flush=True)
    accept = [(c, s) for c, s in cases if s and c["method"] == "limb" and c["diameter"] >= 20 and c["phase"] <= 90]
    if accept:
        bias = np.array([np.abs(s["bias"]) for _, s in accept])
        ratio = np.array([s["ratio"] for _, s in accept])
        rbias = np.array([abs(c["range_err"].mean()) for c, _ in accept])
        chi2_sum = sum(s["chi2_sum"] for _, s in accept)
        dof = 2 * sum(s["n"] for _, s in accept)
        lo, hi = chi2_dist.ppf([0.005, 0.995], dof) / dof
        chi2_mean_sum = sum(s["chi2_mean_sum"] for _, s in accept)
        dof_mean = 2 * sum(s["n"] - 1 for _, s in accept)
        lo_m, hi_m = chi2_dist.ppf([0.005, 0.995], dof_mean) / dof_mean
        print(f"\nacceptance (limb, D >= 20 px, phase <= 90 deg; {len(accept)} cases, {dof // 2} frames):")
        print(f"  centre bias: max |bias| {bias.max():.4f} px (target <= 0.05); cases over 0.05 px: "
              f"{int((bias.max(1) > 0.05).sum())}")
        print(f"  scatter / reported sigma per case and axis: {ratio.min():.2f} .. {ratio.max():.2f} (median "
              f"{np.median(ratio):.2f}; target 0.8 .. 1.2; from {args.seeds} seeds a case a ratio's own standard "
              f"error is ~{1 / math.sqrt(2 * (args.seeds - 1)):.0%}); pooled (whitened, about each case's mean): "
              f"{math.sqrt(chi2_mean_sum / dof_mean):.3f}")
        white = [(c, s) for c, s in accept]
        outside = [(c, s) for c, s in white if s["whitened_hi"] < 0.8 or s["whitened_lo"] > 1.2]
        print(f"  per case, scatter / sigma with each frame whitened by its own covariance (both axes): "
              f"{min(s['whitened'] for _, s in white):.2f} .. {max(s['whitened'] for _, s in white):.2f}; "
              f"{sum(0.8 <= s['whitened'] <= 1.2 for _, s in white)} of {len(white)} cases inside 0.8 .. 1.2; "
              f"cases whose 99 % range misses 0.8 .. 1.2: {len(outside)}"
              + "".join(f"\n    {c['name']} {c['diameter']} px {c['phase']} deg: {s['whitened']:.2f} "
                        f"(99 % range {s['whitened_lo']:.2f} .. {s['whitened_hi']:.2f})" for c, s in outside))
        print(f"  range bias: max {100 * rbias.max():.4f} % (target <= 0.1 %)")
        print(f"  chi-square per dof, pooled: {chi2_sum / dof:.3f} about the truth (target 0.8 .. 1.25; 99 % band "
              f"for {dof} dof {lo:.3f} .. {hi:.3f}); {chi2_mean_sum / dof_mean:.3f} about each case's mean (the "
              f"noise alone; band {lo_m:.3f} .. {hi_m:.3f})")
    if args.basilisk:
        print("\nBasilisk beside opnav on the same Mars frames (error of the centre, px: mean and RMS over seeds)")
        print(f"{'D px':>5s} {'ph':>4s} {'opnav method':12s} {'opnav mean':>16s} {'opnav rms':>9s} "
              f"{'hough n':>7s} {'hough mean':>16s} {'hough rms':>9s} {'limb pts':>8s} {'limb-fit mean':>16s} "
              f"{'limb rms':>8s}")
        for c, s in cases:
            if c["name"] != "mars" or not c["frames"]:
                continue
            res = basilisk_side(args.basilisk, c["frames"])
            hough = np.array([h for h, _, _ in res if h is not None]).reshape(-1, 2)
            limb = np.array([e for _, e, _ in res if e is not None]).reshape(-1, 2)
            npts = int(np.median([n for _, _, n in res]))

            def fmt(e):
                if not len(e):
                    return f"{'none':>16s} {'':>9s}"
                m = e.mean(0)
                return f"({m[0]:6.3f},{m[1]:6.3f}) {math.sqrt(np.mean(np.sum(e * e, 1))):9.3f}"

            ours = fmt(c["errs"]) if s else f"{'failed':>16s} {'':>9s}"
            print(f"{c['diameter']:5d} {c['phase']:4d} {c['method']:12s} {ours} {len(hough):7d} {fmt(hough)} "
                  f"{npts:8d} {fmt(limb)}", flush=True)
    def worst(key, col, method):
        values = [np.nanmedian(c[key][:, col]) for c, s in cases if s and c["method"] == method]
        return 1e3 * max(values) if values else None

    if worst("t_all", 1, "limb") is not None:
        print(f"  limb, 1 MP frame, worst case's median: {worst('t_all', 1, 'limb'):.1f} ms of CPU "
              f"({worst('t_all', 0, 'limb'):.1f} ms wall) the whole centre finding, model images included; "
              f"{worst('t_fit', 1, 'limb'):.1f} ms of CPU ({worst('t_fit', 0, 'limb'):.1f} ms wall) the fit alone "
              f"(one pass, model given; target <= 10 ms)")
    if worst("t_all", 1, "correlation") is not None:
        print(f"  cross-correlation: {worst('t_all', 1, 'correlation'):.1f} ms of CPU "
              f"({worst('t_all', 0, 'correlation'):.1f} ms wall) worst case's median, model image included "
              f"(target <= 30 ms)")


if __name__ == "__main__":
    main()
