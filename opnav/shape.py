"""Triangle-mesh shapes of irregular bodies: a Wavefront OBJ reader, a bounding-volume hierarchy and
the compiled ray casting the renderer's mesh bodies use (:mod:`opnav.bodies`).

A :class:`Mesh` holds its vertices (body-fixed axes, km, origin at the body's centre: the point the
ephemeris gives) and triangles, and on construction builds what every ray needs:

1. **Bounding-volume hierarchy** (:func:`_build_bvh`): the triangles sorted into a binary tree of
   axis-aligned boxes, each node split at the median of its triangles' centroids along its widest
   axis until at most ``_LEAF_SIZE`` triangles are left; stored flat (``int64``/``float64`` arrays)
   for the compiled kernels, which walk it with a small stack.
2. **Ray -> surface** (:func:`_first_hit`): Moeller-Trumbore ray-triangle intersection on the
   leaves the ray's slab test reaches, nearest hit kept. A triangle is hit from either side (a
   closed mesh seen from outside is always first met on its outer side).
3. **Shading** (:func:`_ray_i_over_f`): at the hit, the triangle's own (flat) outward normal gives
   ``mu = cos(emission)`` and ``mu0 = cos(incidence)``; the point is lit when ``mu0 > 0`` and a ray
   from it toward the Sun meets no other triangle (**self-shadowing**: a concave neck, a boulder's
   shadow). The radiance factor (I/F) for geometric albedo ``p`` is ``p (w_L 1.5 mu0 + w_LS 2 mu0 /
   (mu0 + mu))``: Lambert ``(w_L, w_LS) = (1, 0)``, Lommel-Seeliger ``(0, 1)`` and lunar-Lambert
   ``(1 - L, L)`` (McEwen 1991, Icarus 92, 298, with a constant ``L``); each term is normalised to
   I/F = p at zero phase on a disk's centre, so ``p`` is the geometric albedo of every model (the
   ellipsoid renderer's Lambert and Lommel-Seeliger, :func:`opnav.bodies.reflectance`).
4. **Pixel integral** (:func:`mesh_pixel_means`): each pixel's mean I/F on its own rays (bilinear
   interpolation of its corners' gnomonic vectors, as :func:`opnav.bodies.ellipsoid_pixel_means`):
   first ``supersample`` rays per axis everywhere; a pixel whose rays disagree (some on the body and
   some off, some lit and some dark: a limb, the terminator, a shadow's edge) and its neighbours are
   integrated again on ``edge_supersample`` rays per axis, as is every pixel of a body at most
   ``small_px`` across. Unlike an ellipsoid's, a mesh's edges are not found from the corners alone:
   a shadow can fall inside a pixel whose corners are all lit, hence the first pass's rays decide.

Faces are read as given; the OBJ reader checks them (indices in range, no degenerate triangle),
not that the surface is closed or outward-oriented (a normal is turned to face the ray when the
ray meets a triangle's back: the surface seen is always shaded from the side it is seen from).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path

import numpy as np

from .compiled import kernel
from .errors import InputError

#: The shipped synthetic small body (opnav/data/asteroid.README.md says how it was made).
ASTEROID_OBJ = "asteroid.obj"
#: Most triangles in a leaf of the hierarchy.
_LEAF_SIZE = 4
#: Deepest hierarchy the kernels' traversal stack holds (a median split of 10 million triangles
#: into leaves of 4 is 22 levels deep).
_STACK_DEPTH = 64
#: Most faces a mesh may have (memory and load time: a 5,000-triangle shape is 0.2 MB).
MAX_FACES = 5_000_000
#: Rays per pixel per axis on the pixels a mesh's limb, terminator or shadow crosses (and their neighbours).
MESH_EDGE_SUPERSAMPLE = 16
#: A mesh body at most this many pixels across is integrated on the edge grid everywhere.
_SMALL_BODY_PX = 12


@dataclass(frozen=True, eq=False)
class Mesh:
    """A triangle mesh in body-fixed axes (module notes).

    Parameters
    ----------
    vertices_km : (V, 3) array
        Vertex positions, body axes, km, origin at the body's centre (the ephemeris point).
    faces : (F, 3) int array
        Zero-based vertex indices of each triangle.
    source : str
        Where the mesh came from (a file name), for messages.

    Attributes
    ----------
    bounding_radius_km : float
        Largest vertex distance from the origin, km.
    """

    vertices_km: np.ndarray
    faces: np.ndarray
    source: str = "mesh"
    bounding_radius_km: float = field(init=False)

    def __post_init__(self) -> None:
        vertices = np.ascontiguousarray(self.vertices_km, dtype=float)
        faces = np.asarray(self.faces)
        if vertices.ndim != 2 or vertices.shape[1] != 3 or len(vertices) < 4 or not np.all(np.isfinite(vertices)):
            raise InputError(f"{self.source}: a mesh needs at least 4 finite (x, y, z) vertices")
        if faces.ndim != 2 or faces.shape[1] != 3 or len(faces) < 4 or not np.issubdtype(faces.dtype, np.integer):
            raise InputError(f"{self.source}: a mesh needs at least 4 triangles of 3 integer vertex indices")
        if len(faces) > MAX_FACES:
            raise InputError(f"{self.source}: {len(faces)} faces, more than the {MAX_FACES} a mesh may have")
        if faces.min() < 0 or faces.max() >= len(vertices):
            raise InputError(f"{self.source}: a face refers to a vertex that does not exist (indices 0..{len(vertices) - 1})")
        faces = np.ascontiguousarray(faces, dtype=np.int64)
        p0, p1, p2 = vertices[faces[:, 0]], vertices[faces[:, 1]], vertices[faces[:, 2]]
        area2 = np.linalg.norm(np.cross(p1 - p0, p2 - p0), axis=1)
        scale = float(np.max(np.abs(vertices)))
        if not scale > 0 or np.any(area2 <= 1e-14 * scale * scale):
            bad = int(np.argmax(area2 <= 1e-14 * scale * scale)) if scale > 0 else 0
            raise InputError(f"{self.source}: face {bad + 1} is degenerate (zero area)")
        object.__setattr__(self, "vertices_km", vertices)
        object.__setattr__(self, "faces", faces)
        object.__setattr__(self, "bounding_radius_km", float(np.max(np.linalg.norm(vertices, axis=1))))
        object.__setattr__(self, "_arrays", _build_bvh(vertices, faces))

    @property
    def n_faces(self) -> int:
        return len(self.faces)

    def half_extents_km(self) -> tuple[float, float, float]:
        """Largest |x|, |y|, |z| of the vertices, km (a box's semi-axes: the body's ``radii_km``)."""
        return tuple(float(v) for v in np.max(np.abs(self.vertices_km), axis=0))

    def volume_km3(self) -> float:
        """Volume of the closed, outward-oriented surface, km^3 (signed tetrahedra with the origin)."""
        v, f = self.vertices_km, self.faces
        return float(np.einsum("ij,ij->", v[f[:, 0]], np.cross(v[f[:, 1]], v[f[:, 2]])) / 6.0)

    def kernel_arrays(self) -> tuple:
        """The hierarchy and triangles, flat, in the order the kernels take them (module notes)."""
        return self._arrays


def _build_bvh(vertices: np.ndarray, faces: np.ndarray) -> tuple:
    """Step 1 of the module notes: ``(box_lo (N, 3), box_hi (N, 3), child (N,) (-1: leaf; else the first
    child, the second is child + 1), first (N,), count (N,), v0 (F, 3), e1 (F, 3), e2 (F, 3), normal (F, 3))``,
    the triangles reordered so each leaf's are contiguous."""
    p0, p1, p2 = vertices[faces[:, 0]], vertices[faces[:, 1]], vertices[faces[:, 2]]
    lo_tri, hi_tri = np.minimum(np.minimum(p0, p1), p2), np.maximum(np.maximum(p0, p1), p2)
    centroid = (p0 + p1 + p2) / 3.0
    order = np.arange(len(faces))
    box_lo, box_hi, child, first, count = [], [], [], [], []
    # nodes made breadth-first in pairs, so a node's two children sit side by side
    queue = [(0, len(faces))]
    head = 0
    while head < len(queue):
        start, stop = queue[head]
        idx = order[start:stop]
        box_lo.append(lo_tri[idx].min(0))
        box_hi.append(hi_tri[idx].max(0))
        first.append(start)
        count.append(stop - start)
        if stop - start <= _LEAF_SIZE:
            child.append(-1)
        else:
            spread = centroid[idx].max(0) - centroid[idx].min(0)
            axis = int(np.argmax(spread))
            order[start:stop] = idx[np.argsort(centroid[idx, axis], kind="stable")]
            middle = (start + stop) // 2
            child.append(len(queue))
            queue += [(start, middle), (middle, stop)]
        head += 1
    tri = faces[order]
    q0, q1, q2 = vertices[tri[:, 0]], vertices[tri[:, 1]], vertices[tri[:, 2]]
    normal = np.cross(q1 - q0, q2 - q0)
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    return (np.array(box_lo), np.array(box_hi), np.array(child, np.int64), np.array(first, np.int64),
            np.array(count, np.int64), np.ascontiguousarray(q0), np.ascontiguousarray(q1 - q0),
            np.ascontiguousarray(q2 - q0), np.ascontiguousarray(normal))


def read_obj(path: str | Path, *, scale_km: float = 1.0) -> Mesh:
    """A :class:`Mesh` from a Wavefront OBJ file.

    Parameters
    ----------
    path : str or Path
        The file: ``v x y z`` vertex lines and ``f i j k ...`` face lines (one-based indices, negative
        ones counting back from the last vertex read, ``i/t/n`` forms taken by their first number;
        polygons of more than 3 vertices split into a fan of triangles). Other statements (``vn``,
        ``vt``, ``g``, ``o``, ``s``, ``usemtl``, ``mtllib``) and ``#`` comments are skipped.
    scale_km : float
        Kilometres per file unit (1 for a file in km, 0.001 for one in metres).

    Raises
    ------
    InputError
        One line naming the file and the line at fault (or the file that cannot be read).
    """
    path = Path(path)
    if not (math.isfinite(scale_km) and scale_km > 0):
        raise InputError(f"{path}: scale_km must be a positive number, got {scale_km!r}")
    try:
        text = path.read_text(encoding="utf-8", errors="strict")
    except FileNotFoundError:
        raise InputError(f"{path}: no such shape file (a Wavefront OBJ of v and f lines)") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"{path}: cannot read the shape file as text ({exc.__class__.__name__})") from None
    vertices: list[tuple[float, float, float]] = []
    faces: list[tuple[int, int, int]] = []
    for number, line in enumerate(text.splitlines(), start=1):
        words = line.split("#", 1)[0].split()
        if not words or words[0] != "v" and words[0] != "f":
            continue
        where = f"{path}, line {number}"
        if words[0] == "v":
            try:
                xyz = tuple(float(w) for w in words[1:4])
            except ValueError:
                raise InputError(f"{where}: a vertex needs three numbers, got {line.strip()!r}") from None
            if len(xyz) != 3 or not all(math.isfinite(c) for c in xyz):
                raise InputError(f"{where}: a vertex needs three finite numbers, got {line.strip()!r}")
            vertices.append(xyz)
            continue
        if len(words) < 4:
            raise InputError(f"{where}: a face needs at least three vertices, got {line.strip()!r}")
        corners = []
        for word in words[1:]:
            try:
                index = int(word.split("/", 1)[0])
            except ValueError:
                raise InputError(f"{where}: face vertex {word!r} is not an integer index") from None
            resolved = index - 1 if index > 0 else len(vertices) + index
            if index == 0 or not 0 <= resolved < len(vertices):
                raise InputError(f"{where}: face vertex {index} does not exist ({len(vertices)} vertices read so far)")
            corners.append(resolved)
        faces += [(corners[0], corners[k], corners[k + 1]) for k in range(1, len(corners) - 1)]
    if len(vertices) < 4 or len(faces) < 4:
        raise InputError(f"{path}: not a closed mesh: {len(vertices)} vertices and {len(faces)} triangles "
                         "(a Wavefront OBJ of v and f lines, at least 4 of each)")
    return Mesh(np.array(vertices) * scale_km, np.array(faces, dtype=np.int64), source=str(path))


@functools.lru_cache(maxsize=8)
def _cached_obj(path: str, mtime_ns: int, size: int, scale_km: float) -> Mesh:
    return read_obj(path, scale_km=scale_km)


def load_obj(path: str | Path, *, scale_km: float = 1.0) -> Mesh:
    """:func:`read_obj`, kept in memory per (file, modification time, size, scale): a run's frames
    and its worker processes' share one hierarchy instead of building it per body model."""
    path = Path(path)
    try:
        stat = path.stat()
    except OSError:
        return read_obj(path, scale_km=scale_km)  # its one-line error
    return _cached_obj(str(path.resolve()), stat.st_mtime_ns, stat.st_size, float(scale_km))


def shipped_shape(name: str = ASTEROID_OBJ) -> Path:
    """Path of a shape file shipped in ``opnav/data`` (installed with the package)."""
    return Path(str(resources.files("opnav") / "data" / name))


def reflectance_weights(shading: str, lunar_lambert_l: float = 0.5) -> tuple[float, float]:
    """``(w_L, w_LS)`` of the module notes (step 3) for ``shading`` (lambert, lommel-seeliger, lunar-lambert)."""
    if shading == "lambert":
        return 1.0, 0.0
    if shading == "lommel-seeliger":
        return 0.0, 1.0
    if shading == "lunar-lambert":
        return 1.0 - lunar_lambert_l, lunar_lambert_l
    raise InputError(f"a mesh body's shading must be lambert, lommel-seeliger or lunar-lambert, got {shading!r}")


# ----------------------------------------------------------------------------- compiled kernels
@kernel
def _first_hit(o0, o1, o2, d0, d1, d2, box_lo, box_hi, child, first, count, v0, e1, e2, skip,
               any_hit):  # pragma: no cover - compiled
    """(distance along ``d`` in units of |d|, triangle) of the ray ``o + t d``'s nearest hit with t > 0
    (-1 when it misses); ``any_hit``: stop at the first hit found (a shadow ray); ``skip``: a triangle
    never hit (the one the ray leaves)."""
    inv0 = 1.0 / d0 if d0 != 0.0 else 1e300
    inv1 = 1.0 / d1 if d1 != 0.0 else 1e300
    inv2 = 1.0 / d2 if d2 != 0.0 else 1e300
    best_t = math.inf
    best = -1
    stack = np.empty(_STACK_DEPTH, np.int64)
    stack[0] = 0
    top = 1
    while top > 0:
        top -= 1
        node = stack[top]
        # slab test: the ray's t interval inside the node's box
        ta = (box_lo[node, 0] - o0) * inv0
        tb = (box_hi[node, 0] - o0) * inv0
        tmin, tmax = min(ta, tb), max(ta, tb)
        ta = (box_lo[node, 1] - o1) * inv1
        tb = (box_hi[node, 1] - o1) * inv1
        tmin, tmax = max(tmin, min(ta, tb)), min(tmax, max(ta, tb))
        ta = (box_lo[node, 2] - o2) * inv2
        tb = (box_hi[node, 2] - o2) * inv2
        tmin, tmax = max(tmin, min(ta, tb)), min(tmax, max(ta, tb))
        if tmax < max(tmin, 0.0) or tmin > best_t:
            continue
        c = child[node]
        if c >= 0:
            stack[top] = c
            stack[top + 1] = c + 1
            top += 2
            continue
        for k in range(first[node], first[node] + count[node]):
            if k == skip:
                continue
            # Moeller-Trumbore
            p0 = d1 * e2[k, 2] - d2 * e2[k, 1]
            p1 = d2 * e2[k, 0] - d0 * e2[k, 2]
            p2 = d0 * e2[k, 1] - d1 * e2[k, 0]
            det = e1[k, 0] * p0 + e1[k, 1] * p1 + e1[k, 2] * p2
            if det == 0.0:
                continue
            inv = 1.0 / det
            s0, s1, s2 = o0 - v0[k, 0], o1 - v0[k, 1], o2 - v0[k, 2]
            u = (s0 * p0 + s1 * p1 + s2 * p2) * inv
            if u < 0.0 or u > 1.0:
                continue
            q0 = s1 * e1[k, 2] - s2 * e1[k, 1]
            q1 = s2 * e1[k, 0] - s0 * e1[k, 2]
            q2 = s0 * e1[k, 1] - s1 * e1[k, 0]
            v = (d0 * q0 + d1 * q1 + d2 * q2) * inv
            if v < 0.0 or u + v > 1.0:
                continue
            t = (e2[k, 0] * q0 + e2[k, 1] * q1 + e2[k, 2] * q2) * inv
            if 0.0 < t < best_t:
                best_t, best = t, k
                if any_hit:
                    return t, k
    return (best_t if best >= 0 else -1.0), best


@kernel
def _ray_i_over_f(o0, o1, o2, d0, d1, d2, sun, box_lo, box_hi, child, first, count, v0, e1, e2, normal, w_l, w_ls,
                  albedo, shadow_eps):  # pragma: no cover - compiled
    """(I/F, hit) of the ray ``o + t d`` (body axes, km; ``d`` any length): step 3 of the module notes.
    ``hit`` 0: it misses the body; 1: it meets the body in shade (turned away or shadowed); 2: lit."""
    t, k = _first_hit(o0, o1, o2, d0, d1, d2, box_lo, box_hi, child, first, count, v0, e1, e2, -1, False)
    if k < 0:
        return 0.0, 0
    n0, n1, n2 = normal[k, 0], normal[k, 1], normal[k, 2]
    norm_d = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
    mu = -(d0 * n0 + d1 * n1 + d2 * n2) / norm_d
    if mu < 0.0:  # the triangle's back: the side seen is the one facing the ray
        n0, n1, n2, mu = -n0, -n1, -n2, -mu
    mu0 = n0 * sun[0] + n1 * sun[1] + n2 * sun[2]
    if mu <= 0.0 or mu0 <= 0.0:
        return 0.0, 1
    # shadow ray from just off the surface toward the Sun
    h0 = o0 + t * d0 + shadow_eps * n0
    h1 = o1 + t * d1 + shadow_eps * n1
    h2 = o2 + t * d2 + shadow_eps * n2
    _, blocker = _first_hit(h0, h1, h2, sun[0], sun[1], sun[2], box_lo, box_hi, child, first, count, v0, e1, e2, k,
                            True)
    if blocker >= 0:
        return 0.0, 1
    return albedo * (w_l * 1.5 * mu0 + w_ls * 2.0 * mu0 / (mu0 + mu)), 2


@kernel
def _mesh_rays_kernel(los, e1g, e2g, step, n, lo2, hi2, axes, origin_body, sun, box_lo, box_hi, child, first, count,
                      v0, e1, e2, normal, w_l, w_ls, albedo, shadow_eps):  # pragma: no cover - compiled
    """The ray grid of :func:`opnav.bodies._lit_rays_kernel` (rays with lo2 <= a^2 + b^2 <= hi2, row-major;
    ICRF unit vectors, solid angles) and the I/F each carries from the mesh."""
    rays = np.empty((n * n, 3))
    solid = np.empty(n * n)
    i_over_f = np.zeros(n * n)
    k = 0
    for row in range(n):
        b = (row - (n - 1) / 2.0) * step
        for col in range(n):
            a = (col - (n - 1) / 2.0) * step
            radius2 = b * b + a * a
            if not (lo2 <= radius2 <= hi2):
                continue
            scale = 1.0 + radius2
            root = math.sqrt(scale)
            r0 = (los[0] + a * e1g[0] + b * e2g[0]) / root
            r1 = (los[1] + a * e1g[1] + b * e2g[1]) / root
            r2 = (los[2] + a * e1g[2] + b * e2g[2]) / root
            rays[k, 0], rays[k, 1], rays[k, 2] = r0, r1, r2
            solid[k] = step * step / scale**1.5
            d0 = r0 * axes[0, 0] + r1 * axes[1, 0] + r2 * axes[2, 0]
            d1 = r0 * axes[0, 1] + r1 * axes[1, 1] + r2 * axes[2, 1]
            d2 = r0 * axes[0, 2] + r1 * axes[1, 2] + r2 * axes[2, 2]
            value, _ = _ray_i_over_f(origin_body[0], origin_body[1], origin_body[2], d0, d1, d2, sun, box_lo, box_hi,
                                     child, first, count, v0, e1, e2, normal, w_l, w_ls, albedo, shadow_eps)
            i_over_f[k] = value
            k += 1
    return rays[:k].copy(), solid[:k].copy(), i_over_f[:k].copy()


def mesh_lit_rays(mesh: Mesh, grid: tuple, axes: np.ndarray, origin_body_km: np.ndarray, sun_body: np.ndarray, *,
                  weights: tuple[float, float], albedo: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """ICRF unit rays (M, 3), their solid angles (M,) and I/F (M,) of a gnomonic ray grid
    ``grid = (los, e1, e2, step, n, lo2, hi2)`` (:func:`opnav.bodies._lit_rays`) on the mesh whose
    axes (ICRF columns) are ``axes``, seen from ``origin_body_km`` (body axes, km), lit from the
    unit vector ``sun_body`` (body axes)."""
    los, e1, e2, step, n, lo2, hi2 = grid
    return _mesh_rays_kernel(np.ascontiguousarray(los, float), np.ascontiguousarray(e1, float),
                             np.ascontiguousarray(e2, float), float(step), int(n), float(lo2), float(hi2),
                             np.ascontiguousarray(axes, float), np.ascontiguousarray(origin_body_km, float),
                             np.ascontiguousarray(sun_body, float), *mesh.kernel_arrays(), float(weights[0]),
                             float(weights[1]), float(albedo), _shadow_eps(mesh))


def _shadow_eps(mesh: Mesh) -> float:
    """How far off the surface a shadow ray starts, km: a millionth of the body (far above round-off at
    the hit, far below any feature)."""
    return 1e-6 * mesh.bounding_radius_km


@kernel
def _mesh_pixel_kernel(gnomonic, origin, sun, box_lo, box_hi, child, first, count, v0, e1, e2, normal, w_l, w_ls,
                       albedo, shadow_eps, ss, edge_ss, small, los, lo2, hi2, banded,
                       wanted):  # pragma: no cover - compiled
    """Mean I/F of each ``wanted`` pixel (step 4 of the module notes)."""
    hp, wp = gnomonic.shape[0], gnomonic.shape[1]
    h, w = hp - 1, wp - 1
    out = np.zeros((h, w))
    mixed = np.zeros((h, w), np.bool_)
    for i in range(h):
        for j in range(w):
            if not wanted[i, j]:
                continue
            acc, n_hit, n_lit, n_ray = _pixel_rays(gnomonic, i, j, ss, origin, sun, box_lo, box_hi, child, first,
                                                   count, v0, e1, e2, normal, w_l, w_ls, albedo, shadow_eps, los,
                                                   lo2, hi2, banded)
            out[i, j] = acc / (ss * ss)
            if small or (0 < n_hit < n_ray) or (0 < n_lit < n_hit):
                for di in range(max(i - 1, 0), min(i + 2, h)):
                    for dj in range(max(j - 1, 0), min(j + 2, w)):
                        mixed[di, dj] = True
    if edge_ss > ss:
        for i in range(h):
            for j in range(w):
                if wanted[i, j] and mixed[i, j]:
                    acc, _, _, _ = _pixel_rays(gnomonic, i, j, edge_ss, origin, sun, box_lo, box_hi, child, first,
                                               count, v0, e1, e2, normal, w_l, w_ls, albedo, shadow_eps, los, lo2,
                                               hi2, banded)
                    out[i, j] = acc / (edge_ss * edge_ss)
    return out


@kernel(inline=True)
def subpixel_ray(gnomonic, i, j, u, v):  # pragma: no cover - compiled
    """Direction (camera frame, not unit) of the point (u, v) in [0, 1]^2 of pixel (i, j): the bilinear
    blend of the gnomonic corner rays ``gnomonic[i:i+2, j:j+2]`` (the ellipsoid and mesh pixel kernels)."""
    w00, w01, w10, w11 = (1 - u) * (1 - v), u * (1 - v), (1 - u) * v, u * v
    d0 = (w00 * gnomonic[i, j, 0] + w01 * gnomonic[i, j + 1, 0] + w10 * gnomonic[i + 1, j, 0]
          + w11 * gnomonic[i + 1, j + 1, 0])
    d1 = (w00 * gnomonic[i, j, 1] + w01 * gnomonic[i, j + 1, 1] + w10 * gnomonic[i + 1, j, 1]
          + w11 * gnomonic[i + 1, j + 1, 1])
    d2 = (w00 * gnomonic[i, j, 2] + w01 * gnomonic[i, j + 1, 2] + w10 * gnomonic[i + 1, j, 2]
          + w11 * gnomonic[i + 1, j + 1, 2])
    return d0, d1, d2


@kernel(inline=True)
def outside_band(d0, d1, d2, los, lo2, hi2):  # pragma: no cover - compiled
    """True when ray (d0, d1, d2) points away from ``los`` or its squared tangent off ``los`` is
    outside [lo2, hi2] (the limb band a render is restricted to)."""
    along = d0 * los[0] + d1 * los[1] + d2 * los[2]
    tan2 = (d0 * d0 + d1 * d1 + d2 * d2) / (along * along) - 1.0
    return along <= 0.0 or tan2 < lo2 or tan2 > hi2


@kernel
def _pixel_rays(gnomonic, i, j, n, origin, sun, box_lo, box_hi, child, first, count, v0, e1, e2, normal, w_l, w_ls,
                albedo, shadow_eps, los, lo2, hi2, banded):  # pragma: no cover - compiled
    """(sum of I/F, rays on the body, rays lit, rays cast) of pixel (i, j) on ``n`` x ``n`` rays."""
    acc = 0.0
    n_hit = 0
    n_lit = 0
    n_ray = 0
    for ky in range(n):
        v = (ky + 0.5) / n
        for kx in range(n):
            u = (kx + 0.5) / n
            d0, d1, d2 = subpixel_ray(gnomonic, i, j, u, v)
            if banded and outside_band(d0, d1, d2, los, lo2, hi2):
                continue
            n_ray += 1
            value, state = _ray_i_over_f(origin[0], origin[1], origin[2], d0, d1, d2, sun, box_lo, box_hi, child,
                                         first, count, v0, e1, e2, normal, w_l, w_ls, albedo, shadow_eps)
            acc += value
            if state > 0:
                n_hit += 1
            if state == 2:
                n_lit += 1
    return acc, n_hit, n_lit, n_ray


def mesh_pixel_means(gnomonic_body: np.ndarray, origin_body_km: np.ndarray, mesh: Mesh, sun_body: np.ndarray, *,
                     weights: tuple[float, float], albedo: float = 1.0, supersample: int, size_px: float,
                     wanted: np.ndarray | None = None, band=None,
                     edge_supersample: int = MESH_EDGE_SUPERSAMPLE) -> np.ndarray:
    """Mean I/F over each pixel of a box, on the pixels' own rays (step 4 of the module notes): the mesh
    counterpart of :func:`opnav.bodies.ellipsoid_pixel_means`, with the same arguments.

    Parameters
    ----------
    gnomonic_body : (H + 1, W + 1, 3) array
        The box's pixel corners as camera-frame lines of sight scaled to unit boresight component,
        turned into the body's axes; corner ``[i, j]`` is the top-left corner of pixel ``[i, j]``.
    origin_body_km : (3,) array
        The camera's position in the body's axes, km (body centre at the origin).
    mesh : Mesh
    sun_body : (3,) array
        Unit vector body -> Sun in the body's axes.
    weights : (w_L, w_LS)
        :func:`reflectance_weights`; ``albedo`` the geometric albedo (1: I/F per unit albedo).
    supersample : int
        Rays per pixel per axis on the first pass.
    size_px : float
        The body's apparent diameter, px (at most ``_SMALL_BODY_PX``: every pixel on the edge grid).
    wanted : (H, W) bool array, optional
        Integrate only these pixels (the others are 0).
    band : (los_body, (inner, outer)), optional
        Only rays between these angles (rad) from the unit vector ``los_body`` (body axes).
    edge_supersample : int
        Rays per pixel per axis where the first pass's rays disagree, and around those pixels.
    """
    gnomonic_body = np.ascontiguousarray(gnomonic_body, dtype=float)
    h, w = gnomonic_body.shape[0] - 1, gnomonic_body.shape[1] - 1
    wanted = np.ones((h, w), bool) if wanted is None else np.ascontiguousarray(wanted, dtype=bool)
    if band is None:
        los, lo2, hi2 = np.zeros(3), -1.0, math.inf
    else:
        los, (inner, outer) = np.asarray(band[0], float), band[1]
        lo2, hi2 = math.tan(inner) ** 2, math.tan(min(outer, 1.5)) ** 2
    return _mesh_pixel_kernel(gnomonic_body, np.ascontiguousarray(origin_body_km, float),
                              np.ascontiguousarray(sun_body, float), *mesh.kernel_arrays(), float(weights[0]),
                              float(weights[1]), float(albedo), _shadow_eps(mesh), int(supersample),
                              max(int(edge_supersample), int(supersample)), bool(size_px <= _SMALL_BODY_PX), los,
                              lo2, hi2, band is not None, wanted)


def ray_i_over_f(mesh: Mesh, origin_body_km: np.ndarray, dirs_body: np.ndarray, sun_body: np.ndarray, *,
                 weights: tuple[float, float], albedo: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """I/F (N,) and state (N,: 0 off the body, 1 on it in shade, 2 lit) of rays ``dirs_body`` (N, 3, body
    axes) from ``origin_body_km`` (body axes, km): the kernels' shading for a few rays (tests, checks)."""
    dirs = np.atleast_2d(np.asarray(dirs_body, float))
    arrays = mesh.kernel_arrays()
    out, state = np.zeros(len(dirs)), np.zeros(len(dirs), np.int64)
    o = np.asarray(origin_body_km, float)
    sun = np.ascontiguousarray(sun_body, float)
    for k, d in enumerate(dirs):
        out[k], state[k] = _ray_i_over_f(o[0], o[1], o[2], d[0], d[1], d[2], sun, *arrays, float(weights[0]),
                                         float(weights[1]), float(albedo), _shadow_eps(mesh))
    return out, state
