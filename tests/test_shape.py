"""Triangle meshes: the OBJ reader, its one-line errors, the hierarchy's ray casting against brute force,
self-shadowing, and the shipped shape against the tool that made it."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest

from opnav.errors import InputError
from opnav.shape import Mesh, load_obj, ray_i_over_f, read_obj, shipped_shape

ROOT = Path(__file__).resolve().parents[1]


def _tool():
    spec = importlib.util.spec_from_file_location("make_asteroid_mesh", ROOT / "tools" / "make_asteroid_mesh.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_shipped_shape_is_what_its_tool_makes():
    """opnav/data/asteroid.README.md says the tool made the file: regenerated, every vertex agrees to
    the file's 6 decimals (1 mm) and the faces are the same."""
    vertices, faces = _tool().make_mesh()
    mesh = read_obj(shipped_shape())
    assert mesh.n_faces == len(faces) == 5120
    np.testing.assert_array_equal(mesh.faces, faces)
    assert np.max(np.abs(mesh.vertices_km - vertices)) <= 5.01e-7
    # origin at the volume centroid (to the file's rounding), faces outward: positive volume
    assert mesh.volume_km3() == pytest.approx(2.4736, rel=1e-3)
    v, f = mesh.vertices_km, mesh.faces
    assert np.linalg.norm(_tool().volume_centroid(v, f)) < 1e-5
    assert shipped_shape().stat().st_size < 500_000


def test_obj_reader_takes_polygons_slashes_negative_indices_and_comments(tmp_path):
    path = tmp_path / "cube.obj"
    cube = [(x, y, z) for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]
    quads = ["1 2 4 3", "5 7 8 6", "1 5 6 2", "3 4 8 7", "1 3 7 5", "2 6 8 4"]
    text = ["# a cube in metres", "o cube", "mtllib none.mtl"]
    text += [f"v {x} {y} {z}" for x, y, z in cube]
    text += ["vn 0 0 1", "vt 0 0", "s off"]
    text += ["f " + " ".join(f"{i}/1/1" for i in q.split()) for q in quads[:3]]
    text += ["f " + " ".join(str(int(i) - 9) for i in q.split()) + "  # relative" for q in quads[3:]]
    path.write_text("\n".join(text) + "\n")
    mesh = read_obj(path, scale_km=0.001)
    assert mesh.n_faces == 12
    assert mesh.bounding_radius_km == pytest.approx(np.sqrt(3) * 0.001)
    assert abs(mesh.volume_km3()) == pytest.approx(8e-9, rel=1e-12)
    assert load_obj(path, scale_km=0.001) is load_obj(path, scale_km=0.001)


@pytest.mark.parametrize("lines, message", [
    (["v 0 0 0", "v 1 0 0", "v 0 1 zero"], r"bad\.obj, line 3: a vertex needs three numbers"),
    (["v 0 0 0", "v 1 0 0", "v 0 1 0", "v 0 0 1", "f 1 2 5"], r"bad\.obj, line 5: face vertex 5 does not exist"),
    (["v 0 0 0", "v 1 0 0", "v 0 1 0", "v 0 0 1", "f 1 2"], r"bad\.obj, line 5: a face needs at least three"),
    (["v 0 0 0", "v 1 0 0", "v 0 1 0", "v 0 0 1", "f 1 2 x"], r"bad\.obj, line 5: face vertex 'x'"),
    (["v 0 0 nan"], r"bad\.obj, line 1: a vertex needs three finite numbers"),
    (["v 0 0 0", "v 1 0 0", "v 0 1 0", "v 0 0 1", "f 1 2 3"], r"bad\.obj: not a closed mesh: 4 vertices and 1"),
    (["v 0 0 0", "v 1 0 0", "v 2 0 0", "v 0 0 1", "f 1 2 3", "f 1 2 4", "f 1 3 4", "f 2 3 4"],
     r"bad\.obj: face 1 is degenerate"),
])
def test_a_bad_obj_file_is_one_line_naming_the_file_and_line(tmp_path, lines, message):
    path = tmp_path / "bad.obj"
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(InputError, match=message) as info:
        read_obj(path)
    assert "\n" not in str(info.value)


def test_a_missing_or_binary_obj_file_is_one_line(tmp_path):
    with pytest.raises(InputError, match=r"nothere\.obj: no such shape file"):
        read_obj(tmp_path / "nothere.obj")
    binary = tmp_path / "binary.obj"
    binary.write_bytes(b"\x89PNG\r\n\x1a\n\xff\xfe" * 10)
    with pytest.raises(InputError, match=r"binary\.obj: cannot read the shape file as text"):
        read_obj(binary)


def _brute_force_hits(mesh: Mesh, origin, dirs):
    """Nearest hit distance of each ray by testing every triangle (numpy, no hierarchy)."""
    v, f = mesh.vertices_km, mesh.faces
    p0, e1, e2 = v[f[:, 0]], v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]
    out = []
    for d in dirs:
        p = np.cross(d, e2)
        det = np.einsum("ij,ij->i", e1, p)
        s = origin - p0
        u = np.einsum("ij,ij->i", s, p) / det
        q = np.cross(s, e1)
        w = q @ d / det
        t = np.einsum("ij,ij->i", e2, q) / det
        ok = (u >= 0) & (u <= 1) & (w >= 0) & (u + w <= 1) & (t > 0)
        out.append(t[ok].min() if ok.any() else np.inf)
    return np.array(out)


def test_hierarchy_hits_are_brute_force_hits():
    """Rays from a camera 5 km out toward random points about the shipped body: the same rays hit
    and miss as when every triangle is tested, and lit ones are lit where the hit's facet faces the Sun."""
    from opnav.shape import _first_hit

    mesh = read_obj(shipped_shape())
    rng = np.random.default_rng(7)
    origin = np.array([3.0, -4.0, 1.0])
    targets = rng.uniform(-1.4, 1.4, (400, 3))
    dirs = targets - origin
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    expected = _brute_force_hits(mesh, origin, dirs)
    arrays = mesh.kernel_arrays()
    got = np.array([_first_hit(*origin, *d, *arrays[:8], -1, False)[0] for d in dirs])
    got[got < 0] = np.inf
    assert np.sum(np.isfinite(expected)) > 100 and np.sum(~np.isfinite(expected)) > 50
    np.testing.assert_array_equal(np.isfinite(got), np.isfinite(expected))
    hit = np.isfinite(expected)
    np.testing.assert_allclose(got[hit], expected[hit], rtol=1e-12)


def _sphere(centre, radius, subdivisions=3):
    u, f = _tool().icosphere(subdivisions)
    return u * radius + np.asarray(centre, float), f


def test_a_body_in_another_s_shadow_is_dark():
    """Two spheres on the Sun line (+x), seen from +y: every ray to the far one's sunward cap is
    shadowed by the near one (its shadow is a cylinder of the near sphere's radius, wider than the far
    one's cap), while the near one's are lit; alone, the far sphere's cap is lit."""
    va, fa = _sphere((3.0, 0.0, 0.0), 1.0)
    vb, fb = _sphere((-3.0, 0.0, 0.0), 0.8)
    pair = Mesh(np.vstack([va, vb]), np.vstack([fa, fb + len(va)]), source="pair")
    alone = Mesh(vb, fb, source="alone")
    sun = np.array([1.0, 0.0, 0.0])
    origin = np.array([0.0, 50.0, 0.0])
    # rays toward points of each sphere's sunward side (x offset +0.5 of its radius, a ring)
    angles = np.linspace(0, 2 * np.pi, 24, endpoint=False)

    def rays_to(centre, radius):
        pts = centre + radius * np.column_stack([np.full(24, 0.5), 0.6 * np.cos(angles), 0.6 * np.sin(angles)])
        pts = pts[pts[:, 1] > centre[1] - 0.1 * radius]  # the half seen from +y
        d = pts - origin
        return d / np.linalg.norm(d, axis=1, keepdims=True)

    weights = (1.0, 0.0)
    near, near_state = ray_i_over_f(pair, origin, rays_to(np.array([3.0, 0, 0]), 1.0), sun, weights=weights)
    far, far_state = ray_i_over_f(pair, origin, rays_to(np.array([-3.0, 0, 0]), 0.8), sun, weights=weights)
    lone, lone_state = ray_i_over_f(alone, origin, rays_to(np.array([-3.0, 0, 0]), 0.8), sun, weights=weights)
    assert np.all(near_state == 2) and np.all(near > 0)
    assert np.all(far_state == 1) and np.all(far == 0)
    assert np.all(lone_state == 2) and np.all(lone > 0)


def test_mesh_refuses_bad_arrays():
    v, f = _sphere((0, 0, 0), 1.0, 1)
    with pytest.raises(InputError, match="refers to a vertex that does not exist"):
        Mesh(v, f + 1)
    with pytest.raises(InputError, match="finite"):
        Mesh(np.where(v > 0.9, np.nan, v), f)
    with pytest.raises(InputError, match="integer"):
        Mesh(v, f.astype(float))
