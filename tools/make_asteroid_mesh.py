"""Write opnav's shipped small-body shape model, ``opnav/data/asteroid.obj`` (a Wavefront OBJ, km).

The shape is made here, not measured: an irregular, bilobed ("contact binary") body for the
asteroid-approach sample and the mesh renderer's tests. Steps:

1. An icosphere: the 12 vertices of an icosahedron, each triangle split into four ``SUBDIVISIONS``
   times (4: 2,562 vertices, 5,120 triangles) and the vertices pushed onto the unit sphere.
2. A radius for each vertex direction ``u``: the triaxial ellipsoid of ``SEMI_AXES_KM`` along ``u``,
   times a waist ``1 - WAIST_DEPTH exp(-(u_x / WAIST_WIDTH)^2)`` that pinches the body about its long
   axis (two lobes, a concave neck that shadows itself at phase), times ``exp(h(u))`` with ``h`` a sum
   of real spherical harmonics of degrees 2 to ``MAX_DEGREE`` whose coefficients are normal draws of
   standard deviation ``ROUGHNESS / l^1.5`` from ``numpy.random.default_rng(SEED)`` (a smooth,
   star-shaped surface: every ray from the centre leaves it once).
3. The vertices moved so that the volume centroid (the centre of mass of a uniform body: the point an
   ephemeris gives) is the origin, from the signed tetrahedra of the triangles with the origin.

Run from the repository's root (``python tools/make_asteroid_mesh.py``); the file is the same on
every run (``tests/test_shape.py`` regenerates it and compares). Faces are counter-clockwise seen
from outside (outward normals by the right-hand rule).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from scipy.special import sph_harm_y

SEED = 20260038
SUBDIVISIONS = 4
SEMI_AXES_KM = (1.30, 0.80, 0.65)
WAIST_DEPTH = 0.30
WAIST_WIDTH = 0.30
MAX_DEGREE = 8
ROUGHNESS = 0.10
OUT = Path(__file__).resolve().parents[1] / "opnav" / "data" / "asteroid.obj"


def icosphere(subdivisions: int) -> tuple[np.ndarray, np.ndarray]:
    """Unit-sphere vertices (V, 3) and counter-clockwise triangles (F, 3) of a subdivided icosahedron."""
    t = (1.0 + 5.0**0.5) / 2.0
    verts = [(-1, t, 0), (1, t, 0), (-1, -t, 0), (1, -t, 0), (0, -1, t), (0, 1, t), (0, -1, -t), (0, 1, -t),
             (t, 0, -1), (t, 0, 1), (-t, 0, -1), (-t, 0, 1)]
    faces = [(0, 11, 5), (0, 5, 1), (0, 1, 7), (0, 7, 10), (0, 10, 11), (1, 5, 9), (5, 11, 4), (11, 10, 2),
             (10, 7, 6), (7, 1, 8), (3, 9, 4), (3, 4, 2), (3, 2, 6), (3, 6, 8), (3, 8, 9), (4, 9, 5), (2, 4, 11),
             (6, 2, 10), (8, 6, 7), (9, 8, 1)]
    points = [np.array(v, float) / np.linalg.norm(v) for v in verts]
    for _ in range(subdivisions):
        middle: dict[tuple[int, int], int] = {}

        def mid(i: int, j: int) -> int:
            key = (min(i, j), max(i, j))
            if key not in middle:
                p = points[i] + points[j]
                points.append(p / np.linalg.norm(p))
                middle[key] = len(points) - 1
            return middle[key]

        new = []
        for a, b, c in faces:
            ab, bc, ca = mid(a, b), mid(b, c), mid(c, a)
            new += [(a, ab, ca), (b, bc, ab), (c, ca, bc), (ab, bc, ca)]
        faces = new
    return np.array(points), np.array(faces, dtype=np.int64)


def radius_km(u: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Step 2 of the module notes: the surface's distance from the centre along unit vectors ``u`` (N, 3)."""
    a, b, c = SEMI_AXES_KM
    ellipsoid = 1.0 / np.sqrt((u[:, 0] / a) ** 2 + (u[:, 1] / b) ** 2 + (u[:, 2] / c) ** 2)
    waist = 1.0 - WAIST_DEPTH * np.exp(-((u[:, 0] / WAIST_WIDTH) ** 2))
    theta = np.arccos(np.clip(u[:, 2], -1.0, 1.0))
    phi = np.mod(np.arctan2(u[:, 1], u[:, 0]), 2.0 * np.pi)
    h = np.zeros(len(u))
    for degree in range(2, MAX_DEGREE + 1):
        sigma = ROUGHNESS / degree**1.5
        for order in range(0, degree + 1):
            y = sph_harm_y(degree, order, theta, phi)
            h += sigma * rng.standard_normal() * y.real
            if order > 0:
                h += sigma * rng.standard_normal() * y.imag
    return ellipsoid * waist * np.exp(h)


def volume_centroid(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Centroid of the solid a closed, outward-oriented triangle mesh bounds (step 3)."""
    p0, p1, p2 = vertices[faces[:, 0]], vertices[faces[:, 1]], vertices[faces[:, 2]]
    volume = np.einsum("ij,ij->i", p0, np.cross(p1, p2)) / 6.0
    return np.sum(volume[:, None] * (p0 + p1 + p2) / 4.0, axis=0) / np.sum(volume)


def make_mesh() -> tuple[np.ndarray, np.ndarray]:
    """The shipped shape's vertices (V, 3) km and faces (F, 3), zero-based."""
    rng = np.random.default_rng(SEED)
    unit, faces = icosphere(SUBDIVISIONS)
    vertices = unit * radius_km(unit, rng)[:, None]
    return vertices - volume_centroid(vertices, faces), faces


def obj_text(vertices: np.ndarray, faces: np.ndarray) -> str:
    """The OBJ file's text: a header naming this script and its parameters, ``v`` lines (km, 6 decimals)
    and ``f`` lines (one-based)."""
    header = [
        "# opnav synthetic small body (a generated shape, no real asteroid): tools/make_asteroid_mesh.py",
        f"# seed {SEED}, icosphere subdivisions {SUBDIVISIONS}, semi-axes {SEMI_AXES_KM} km, waist depth "
        f"{WAIST_DEPTH} width {WAIST_WIDTH}, spherical harmonics l = 2..{MAX_DEGREE}, roughness {ROUGHNESS}",
        "# units km; origin at the volume centroid; faces counter-clockwise seen from outside",
        f"# {len(vertices)} vertices, {len(faces)} faces; licence CC0-1.0 (opnav/data/asteroid.README.md)",
    ]
    lines = header + [f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in vertices]
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in faces]
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=OUT, help=f"the OBJ file to write (default {OUT})")
    args = parser.parse_args()
    vertices, faces = make_mesh()
    args.out.write_text(obj_text(vertices, faces))


if __name__ == "__main__":
    main()
