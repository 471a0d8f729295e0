"""Sample frames of image-mode reports: one frame per sensor with what the image stage found on it.

:func:`sample_frames` gives a run report's sample-frame figures:

- S1 (and the demo): the frame ``facts.sample_frame`` names (a FITS file the run wrote), measured
  again by the image stage: its detections, the catalog stars the solved attitude puts on a
  detection (the identified stars), the targets' true centres and their measured positions;
- S3: the star sensor and the UV Earth sensor at the arc's middle epoch, rendered whole (the run
  rendered only the windows and the limb annulus the stage reads) at the true state and attitude
  and measured by the same stage: star sensor detections and identified stars, the Earth's true
  centre and limb and the fitted limb.

Each frame is drawn with a log stretch, pixel (0, 0) the centre of the first pixel, rows upwards.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .report_page import Figure
from .report_plots import figure_png, new_figure

#: A catalog star counts as identified when the solved attitude puts it this close to a detection, px.
IDENTIFIED_PX = 2.0


def frame_figure(image: np.ndarray, title: str, *, detections: np.ndarray, stars: np.ndarray,
                 true_targets=(), measured_targets=(), limbs=(), points=None, marks=(), zoom=None):
    """A frame with overlays, as a matplotlib figure.

    Parameters
    ----------
    image : (H, W) array
        Pixels (NaN where nothing was rendered).
    detections, stars : (N, 2) arrays
        Pixel (x, y) of the stage's detections and of the identified catalog stars.
    true_targets, measured_targets : sequence of (name, (x, y))
        Targets' true centres and the stage's measured centres, px.
    limbs : sequence of (label, colour, (K, 2) array)
        Lines to draw (an Earth sensor's true and fitted limb, px; a label with "true" is dashed).
    points : (M, 2) array, optional
        Limb edge points the fit used, px.
    marks : sequence of (label, colour, marker, (x, y))
        Single points to mark (a navigation star).
    zoom : ((x, y), half_width_px), optional
        A region shown magnified in an inset with the limbs and points (sub-pixel differences).
    """
    pixels = np.asarray(image, dtype=float)
    finite = pixels[np.isfinite(pixels)]
    # the stretch starts two noise sigmas (from the median absolute deviation) above the median, the sky
    # background, so the noise stays dark and faint sources show
    low, high = np.percentile(finite, [50.0, 99.9]) if finite.size else (0.0, 1.0)
    low += 2.0 * 1.4826 * (np.median(np.abs(finite - low)) if finite.size else 0.0)
    fig, axes = new_figure(1, 1, width_in=6.8, height_in=7.0)
    ax = axes[0, 0]
    ax.grid(False)
    image_shown = np.log1p(np.clip(np.nan_to_num(pixels, nan=low) - low, 0.0, None))
    top = np.log1p(max(high - low, 1.0))
    ax.imshow(image_shown, cmap="gray", origin="lower", vmax=top, interpolation="nearest")
    detections = np.asarray(detections, dtype=float).reshape(-1, 2)
    stars = np.asarray(stars, dtype=float).reshape(-1, 2)
    if len(detections):
        ax.scatter(detections[:, 0], detections[:, 1], s=70, facecolors="none", edgecolors="tab:cyan", lw=0.8,
                   label=f"detections ({len(detections)})")
    if len(stars):
        ax.scatter(stars[:, 0], stars[:, 1], s=22, marker="s", facecolors="none", edgecolors="yellow", lw=0.8,
                   label=f"identified stars ({len(stars)})")
    notes = []
    for name, xy in true_targets:
        ax.plot(*xy, "+", color="tab:green", ms=16, mew=1.4)
        notes.append((f"{name} (true)", xy, "tab:green"))
    for name, xy in measured_targets:
        ax.plot(*xy, "x", color="tab:red", ms=11, mew=1.4)
        notes.append((f"{name} (measured)", xy, "tab:red"))
    # targets lie close together (a moon beside Mars): their labels go in a column on the emptier
    # side of the frame, one line apart, each with a leader line to its marker, so none overprints another
    height, width = pixels.shape
    left = not notes or np.mean([float(xy[0]) for _, xy, _ in notes]) > 0.5 * width
    column_x = (0.03 if left else 0.62) * width
    for k, (text, xy, color) in enumerate(sorted(notes, key=lambda m: -float(m[1][1]))):
        ax.annotate(text, xy, xytext=(column_x, (0.40 - 0.05 * k) * height), color=color, fontsize=9,
                    bbox={"boxstyle": "round,pad=0.2", "fc": "black", "ec": "none", "alpha": 0.6},
                    arrowprops={"arrowstyle": "-", "color": color, "lw": 0.7, "shrinkA": 0, "shrinkB": 5})
    for text, color, line in limbs:
        line = np.asarray(line, dtype=float).reshape(-1, 2)
        ax.plot(line[:, 0], line[:, 1], color=color, lw=1.0, ls="--" if "true" in text else "-", label=text)
    if points is not None and len(points):
        points = np.asarray(points, dtype=float).reshape(-1, 2)
        ax.scatter(points[:, 0], points[:, 1], s=3, color="tab:orange", lw=0, label=f"limb edge points ({len(points)})")
    for text, color, marker, xy in marks:
        ax.plot(*xy, marker, color=color, ms=14, mew=1.4, mfc="none", label=text)
    if zoom is not None:
        (zx, zy), half = zoom
        inset = ax.inset_axes([0.03, 0.03, 0.36, 0.36])
        inset.imshow(image_shown, cmap="gray", origin="lower", vmax=top, interpolation="nearest")
        for text, color, line in limbs:
            line = np.asarray(line, dtype=float).reshape(-1, 2)
            inset.plot(line[:, 0], line[:, 1], color=color, lw=2.0 if "true" in text else 1.0,
                       ls="--" if "true" in text else "-")
        if points is not None and len(points):
            inset.scatter(points[:, 0], points[:, 1], s=10, color="tab:orange", lw=0)
        inset.set_xlim(zx - half, zx + half)
        inset.set_ylim(zy - half, zy + half)
        inset.set_xticks([])
        inset.set_yticks([])
        inset.set_title(f"{2 * half:g} x {2 * half:g} px around the limb's top", fontsize=8, color="white", pad=2)
        ax.indicate_inset_zoom(inset, edgecolor="white")
    ax.set_xlim(-0.5, pixels.shape[1] - 0.5)
    ax.set_ylim(-0.5, pixels.shape[0] - 0.5)
    ax.set_xlabel("column x (px)")
    ax.set_ylabel("row y (px)")
    ax.set_title(title, fontsize=10)
    legend = ax.legend(loc="upper right", fontsize=8, framealpha=0.8)
    legend.get_frame().set_facecolor("white")
    return fig


def identified_stars(catalog, camera, R_icrf_cam, detections: np.ndarray, vmag_limit: float | None,
                     t_tdb_s: float, r_observer_ssb_km: np.ndarray, v_observer_ssb_km_s: np.ndarray) -> np.ndarray:
    """Pixel (x, y) (M, 2) of the catalog stars the attitude ``R_icrf_cam`` (camera -> ICRF) puts within
    :data:`IDENTIFIED_PX` of a detection: their apparent directions at ``t_tdb_s`` from the observer at
    ``r_observer_ssb_km`` moving at ``v_observer_ssb_km_s`` (SSB, ICRF)."""
    from scipy.spatial import cKDTree

    detections = np.asarray(detections, dtype=float).reshape(-1, 2)
    if not len(detections):
        return np.empty((0, 2))
    boresight = R_icrf_cam.apply([0.0, 0.0, 1.0])
    rows = catalog.cone(boresight, camera.half_diagonal_fov_rad, vmag_limit=vmag_limit)
    if not rows.size:
        return np.empty((0, 2))
    directions = catalog.apparent_directions(rows, t_tdb_s=t_tdb_s, r_observer_ssb_km=r_observer_ssb_km,
                                             v_observer_ssb_km_s=v_observer_ssb_km_s)
    xy = camera.project(R_icrf_cam.inv().apply(directions))
    xy = xy[np.all(np.isfinite(xy), axis=1) & camera.in_frame(xy)]
    if not len(xy):
        return np.empty((0, 2))
    distance, _ = cKDTree(detections).query(xy)
    return xy[distance <= IDENTIFIED_PX]


def s1_frame_figure(path: str | Path):
    """The S1 frame at ``path`` (FITS with its truth) measured again (module notes): a matplotlib figure."""
    from ..catalog import load_catalog
    from ..ephemeris import default_ephemeris
    from ..image.pipeline import PipelineOptions, frame_input, measure_frame
    from ..render.frames_io import read_frame

    stored = read_frame(path)
    frame = frame_input(path)
    catalog = load_catalog()
    options = PipelineOptions(targets=("phobos", "deimos"))
    result = measure_frame(frame, catalog=catalog, ephemeris=default_ephemeris(), options=options,
                           rng=np.random.default_rng(0), source=str(path))
    detections = np.asarray(result.sources.xy, dtype=float).reshape(-1, 2)[np.asarray(result.sources.ok, dtype=bool)]
    truth = stored.truth
    stars = identified_stars(catalog, frame.camera, result.R_icrf_cam, detections, options.vmag_limit, result.t_tdb_s,
                             truth.r_observer_ssb_km, truth.v_observer_ssb_km_s) if result.n_stars_matched \
        else np.empty((0, 2))
    true = [(t.name, t.xy_cof_px) for t in truth.targets if np.all(np.isfinite(t.xy_cof_px))]
    measured = [(r.target, r.extra["xy_px"]) for r in result.records if r.kind == "radec" and "xy_px" in r.extra]
    return frame_figure(stored.image, f"{Path(path).name}: {result.n_stars_matched} stars matched by the stage",
                        detections=detections, stars=stars, true_targets=true, measured_targets=measured)


def sample_frames(out: Path, summary: dict) -> list:
    """The sample-frame figures of a run report (module notes), or a sentence saying why there is none;
    empty in measurement mode."""
    if summary.get("mode") != "images":
        return []
    facts = summary.get("facts") or {}
    study = summary["run"]["study"]
    figures: list = []
    sample = facts.get("sample_frame")
    if study == "s1" and not (sample and Path(sample).exists()):
        figures.append("No sample frame: the run wrote no frame to disk (`dump_every = 0`), or its frames were "
                       "removed.")
    elif study == "s1":
        figures.append(Figure("sample_frame", f"Sample frame {Path(sample).name} of the camera: the stage's "
                              "detections (cyan), the catalog stars its attitude identified (yellow squares), the "
                              "moons' true centres (green +) and measured centres (red x).",
                              figure_png(s1_frame_figure(sample))))
    if study == "s3":
        star, earth = s3_frame_figures(Path(out), summary)
        figures.append(Figure("sample_frame_star_sensor", "The star sensor at the arc's middle epoch, rendered whole "
                              "and measured by the image stage: detections (cyan), identified stars (yellow "
                              "squares), the scheduled navigation star (magenta circle).", figure_png(star)))
        figures.append(Figure("sample_frame_earth_sensor", "The UV Earth sensor at the same epoch, rendered whole: "
                              "the limb edge points the stage found (orange), the limb it fitted (red) and the "
                              "true visible limb at the calibrated altitude (green, dashed).", figure_png(earth)))
    return figures


def cone_line(camera, R_icrf_cam, centre_icrf: np.ndarray, radius_rad: float, count: int = 361) -> np.ndarray:
    """Pixels (count, 2) of the circle of directions ``radius_rad`` from ``centre_icrf`` (ICRF unit
    vector) seen by ``camera`` at ``R_icrf_cam`` (camera -> ICRF): a limb as the camera draws it."""
    from scipy.spatial.transform import Rotation

    centre = np.asarray(centre_icrf, dtype=float) / np.linalg.norm(centre_icrf)
    helper = np.array([1.0, 0.0, 0.0]) if abs(centre[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    tilt = np.cross(centre, helper)
    tilt *= radius_rad / np.linalg.norm(tilt)
    edge = Rotation.from_rotvec(tilt).apply(centre)
    spin = Rotation.from_rotvec(np.outer(np.linspace(0.0, 2.0 * np.pi, count), centre))
    return camera.project(R_icrf_cam.inv().apply(spin.apply(edge)))


def s3_frame_figures(out: Path, summary: dict):
    """(star sensor, Earth sensor) figures of an S3 image-mode run at its middle epoch (module notes).

    The run rendered only what its stage reads (the tracker's windows, the limb annulus), so these
    are rendered again, whole, at the true state (``out/truth.npz``) and the Earth-pointing attitude,
    with the run's sensors, render and stage settings, and measured with the prior attitude the
    tracker would hold (the true one).
    """
    from ..catalog import load_catalog
    from ..ephemeris.cache import default_cached_ephemeris
    from ..errors import OpnavError
    from ..image.pipeline import FrameInput, measure_frame
    from ..image.targets import fit_limb, limb_points
    from ..light import apparent_direction
    from ..observer import Observer
    from ..render.frame import RenderOptions, render_frame
    from ..sim.stages import predicted_limb
    from .s3 import Settings, star_schedule
    from .s3_images import SKY_DEPTH_MAG, body_attitude, sensors, stage_options

    settings = Settings(**summary["run"]["settings"])
    seed = int(summary["run"]["seed"])
    truth = np.load(out / "truth.npz")
    k = truth["epochs"].size // 2
    t, state = float(truth["epochs"][k]), np.asarray(truth["truth"][k], dtype=float)
    ephemeris = default_cached_ephemeris()
    catalog = load_catalog()
    r_earth, v_earth = ephemeris.state("earth", t)
    observer = Observer(t, r_earth + state[:3], v_earth + state[3:])
    kit = sensors(settings)
    altitude = float(((summary.get("facts") or {}).get("limb_altitude_km") or {}).get("calibrated", 48.0))
    options = stage_options(settings, altitude)
    rng = np.random.default_rng([seed, 35, k])

    # star sensor: the sky the run's frames show (stars below the stage's catalog limit too)
    R_star = body_attitude(state) * kit.body_star
    camera = kit.star_camera
    rendered = render_frame(camera, R_star, observer, catalog=catalog, ephemeris=ephemeris, rng=rng,
                            options=RenderOptions(vmag_limit=settings.star_vmag_limit + SKY_DEPTH_MAG,
                                                  sun_keepout_margin_rad=0.0))
    frame = FrameInput.from_camera(rendered.image, camera, t, R_star, observer, frame_id=f"epoch_{k:06d}")
    result = measure_frame(frame, catalog=catalog, ephemeris=ephemeris, options=options, rng=rng)
    detections = np.asarray(result.sources.xy, dtype=float).reshape(-1, 2)[np.asarray(result.sources.ok, dtype=bool)]
    stars = identified_stars(catalog, camera, result.R_icrf_cam, detections, options.vmag_limit, t,
                             observer.r_ssb_km, observer.v_ssb_km_s) if result.n_stars_matched else np.empty((0, 2))
    row = int(star_schedule(np.asarray(truth["truth"][:k + 1], dtype=float), settings)[0][-1])  # it holds a star
    marks = []
    if row >= 0:
        direction = catalog.apparent_directions([row], t_tdb_s=t, r_observer_ssb_km=observer.r_ssb_km,
                                                v_observer_ssb_km_s=observer.v_ssb_km_s)[0]
        marks.append((f"navigation star HIP {int(catalog.hip[row])}", "magenta", "o",
                      camera.project(R_star.inv().apply(direction))))
    from ..epochs import format_epoch

    when = format_epoch(t, "utc", precision=0).replace("T", " ") + " UTC"
    star = frame_figure(rendered.image, f"star sensor, {when}: {result.n_stars_matched} stars matched",
                        detections=detections, stars=stars, marks=marks)

    # Earth sensor: the Earth alone (a sensor is blinded only by the Sun inside its own field)
    R_earth = body_attitude(state) * kit.body_earth
    camera = kit.earth_camera
    rendered = render_frame(camera, R_earth, observer, targets=("earth",), ephemeris=ephemeris, rng=rng,
                            options=RenderOptions(supersample=2, sun_keepout_margin_rad=0.0))
    centre, radius_px, rho = predicted_limb(camera, R_earth, observer, ephemeris, altitude)
    edge = limb_points(rendered.image, centre, radius_px, radial_half_width_px=settings.limb_band_px)
    earth_icrf = apparent_direction(lambda s: ephemeris.position("earth", s), t, observer.r_ssb_km, observer.v_ssb_km_s)
    limbs = [("true visible limb", "tab:green", cone_line(camera, R_earth, earth_icrf, rho))]
    try:
        fit = fit_limb(edge, camera, rng=rng, velocity_cam_km_s=R_earth.inv().apply(observer.v_ssb_km_s))
        limbs.append(("fitted limb", "tab:red", cone_line(camera, R_earth, R_earth.apply(fit.centre_cam),
                                                           fit.radius_rad)))
    except OpnavError as exc:  # the figure says the fit failed instead of losing the report
        limbs[0] = (f"true visible limb (the fit failed: {exc})", "tab:green", limbs[0][2])
    line = limbs[0][2]
    top = line[np.nanargmax(line[:, 1])]  # the limb's highest point: the inset shows fit and truth there
    earth = frame_figure(rendered.image, f"UV Earth sensor, {when}", detections=np.empty((0, 2)),
                         stars=np.empty((0, 2)), limbs=limbs, points=edge, zoom=(top, 6.0))
    return star, earth
