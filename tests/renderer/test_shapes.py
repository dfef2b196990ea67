"""Shapes: closed-form hits and normals, equivalent shapes agreeing, and invariants shared by every shape."""
from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch

import renderer
from renderer.core.params import SceneError
from renderer.shapes import (Box, Cone, Cylinder, Mesh, Polyhedron, Rectangle, Sphere, build_shape, load_obj)
from renderer.shapes import mesh as mesh_module
from renderer.core.transforms import euler_xyz_deg

SCENES = Path(renderer.__file__).parent / "scenes"
T_MIN = 1e-6
INF = float("inf")
TETRA = [[-1, 0, 0, 0], [0, -1, 0, 0], [0, 0, -1, 0], [1, 1, 1, 1]]  # x, y, z >= 0 and x + y + z <= 1


def cast(shape, o, d, dtype=torch.float64, t_min=T_MIN):
    """Intersect rays given as nested lists; returns t, aux, and (normal, uv) at the hits (NaN on misses)."""
    o = torch.as_tensor(o, dtype=dtype).reshape(-1, 3)
    d = torch.as_tensor(d, dtype=dtype).reshape(-1, 3)
    d = d / torch.linalg.vector_norm(d, dim=-1, keepdim=True)
    t, aux = shape.intersect(o, d, t_min)
    p = o + torch.where(torch.isfinite(t), t, torch.zeros_like(t))[:, None] * d
    normal, uv = shape.surface(p, aux)
    miss = ~torch.isfinite(t)[:, None]
    return t, aux, normal.masked_fill(miss, math.nan), uv.masked_fill(miss, math.nan)


def close(actual, expected, tol=1e-9):
    expected = torch.as_tensor(expected, dtype=actual.dtype)
    return bool(torch.allclose(actual, expected, atol=tol, rtol=0))


def unit_vectors(n, generator):
    return torch.nn.functional.normalize(torch.randn(n, 3, generator=generator, dtype=torch.float64), dim=-1)


def rays_towards(shape, n, generator, dtype=torch.float64):
    """Rays from outside the bounding sphere aimed at random points inside it (most of them hit)."""
    center, radius = shape.bounding_sphere()
    start = center + 3 * radius * unit_vectors(n, generator)
    depth = torch.rand(n, 1, generator=generator, dtype=torch.float64) ** (1 / 3)  # uniform in the ball
    aim = center + 0.9 * radius * depth * unit_vectors(n, generator)
    d = torch.nn.functional.normalize(aim - start, dim=-1)
    return start.to(dtype), d.to(dtype)


def rotated_box_halfspaces(center, size, rotation_deg):
    """The box as six half-spaces ±R[:, a]·x <= ±R[:, a]·center + size_a / 2."""
    R = euler_xyz_deg(rotation_deg)
    c = torch.tensor(center, dtype=torch.float64)
    rows = []
    for a in range(3):
        n = R[:, a]
        for sign in (1.0, -1.0):
            rows.append((sign * n).tolist() + [float(sign * n @ c + size[a] / 2)])
    return rows


# A placed, rotated, non-trivial instance of every shape, for the invariants shared by all of them.
EXAMPLES = {
    "sphere": lambda: Sphere((0.3, -0.2, 1.0), 1.3),
    "box": lambda: Box((1.0, 2.0, 3.0), (2.0, 4.0, 6.0), (30.0, -20.0, 50.0)),
    "cylinder": lambda: Cylinder((1.0, 0.0, -1.0), (1.0, 2.0, 2.0), 0.7, 2.5),
    "cone": lambda: Cone((0.0, 1.0, 0.0), (0.0, -1.0, 1.0), 1.2, 2.0),
    "rectangle": lambda: Rectangle((0.0, 0.0, 5.0), (4.0, 2.0), (10.0, 20.0, 30.0)),
    "mesh": lambda: Mesh.from_obj(str(SCENES / "icosahedron.obj"), center=(0.5, 0.0, 0.0), scale=(1.0, 2.0, 1.5),
                                  rotation_deg=(10.0, 0.0, 40.0)),
    "polyhedron": lambda: Polyhedron(TETRA),
}
SOLIDS = [k for k in EXAMPLES if k != "rectangle"]


# ---------------------------------------------------------------------------------------------- box


def test_box_axis_aligned_hits_and_normals():
    box = Box((1.0, 2.0, 3.0), (2.0, 4.0, 6.0))
    # From 10 units away along each axis, towards the centre: t = 10 − half-size; the normal faces back.
    half = [1.0, 2.0, 3.0]
    for axis in range(3):
        for sign in (-1.0, 1.0):
            o = [1.0, 2.0, 3.0]
            o[axis] += sign * 10
            d = [0.0, 0.0, 0.0]
            d[axis] = -sign
            t, aux, n, _ = cast(box, o, d)
            expected_n = [0.0, 0.0, 0.0]
            expected_n[axis] = sign
            assert close(t, [10 - half[axis]]), f"axis {axis} side {sign}: t = {t.tolist()}, expected {10 - half[axis]}"
            assert close(n, [expected_n]), f"axis {axis} side {sign}: normal {n.tolist()}, expected {expected_n}"
            assert int(aux) == 2 * axis + (sign > 0), f"face index {int(aux)} for axis {axis} side {sign}"


def test_box_ray_from_inside_returns_exit():
    box = Box((1.0, 2.0, 3.0), (2.0, 4.0, 6.0))
    t, _, n, _ = cast(box, [1.0, 2.0, 3.0], [0.0, 1.0, 0.0])
    assert close(t, [2.0]), f"exit from the centre along +y at half the y size, got {t.tolist()}"
    assert close(n, [[0.0, 1.0, 0.0]]), f"exit normal is the outward +y, got {n.tolist()}"


def test_box_misses():
    box = Box((0.0, 0.0, 0.0), (2.0, 2.0, 2.0))
    o = [[0.0, 1.5, -5.0],   # parallel to the y slab, outside it
         [0.0, 0.0, 5.0],    # pointing away
         [5.0, 5.0, -5.0],   # passes beside a corner
         [0.0, 1.0, -5.0]]   # grazing along the y = 1 face counts as inside the slab: hit
    d = [[0.0, 0.0, 1.0], [0.0, 0.0, 1.0], [0.0, 0.0, 1.0], [0.0, 0.0, 1.0]]
    t, _, _, _ = cast(box, o, d)
    assert torch.isinf(t[:3]).all(), f"expected misses, got {t[:3].tolist()}"
    assert close(t[3:], [4.0]), f"a ray in the plane of a face enters through the front face, got {t[3:].tolist()}"


def test_box_respects_t_min():
    box = Box((0.0, 0.0, 0.0), (2.0, 2.0, 2.0))
    t, _, n, _ = cast(box, [0.0, 0.0, -5.0], [0.0, 0.0, 1.0], t_min=4.5)
    assert close(t, [6.0]), f"with t_min past the entry the exit is returned, got {t.tolist()}"
    assert close(n, [[0.0, 0.0, 1.0]]), f"exit normal +z, got {n.tolist()}"
    t, _, _, _ = cast(box, [0.0, 0.0, -5.0], [0.0, 0.0, 1.0], t_min=6.5)
    assert torch.isinf(t).all(), f"nothing beyond the exit, got {t.tolist()}"


def test_box_face_uv_in_scene_units_from_the_corner():
    box = Box((1.0, 2.0, 3.0), (2.0, 4.0, 6.0))
    _, _, _, uv = cast(box, [1.5, 1.0, -10.0], [0.0, 0.0, 1.0])
    assert close(uv, [[1.5, 1.0]]), f"−z face: uv = local (x, y) + size/2 = (1.5, 1.0), got {uv.tolist()}"
    _, _, _, uv = cast(box, [10.0, 3.0, 5.0], [-1.0, 0.0, 0.0])
    assert close(uv, [[3.0, 5.0]]), f"+x face: uv = local (y, z) + size/2 = (3, 5), got {uv.tolist()}"


def test_rotated_box_equals_polyhedron():
    center, size, rot = (1.0, -2.0, 0.5), (1.0, 2.0, 3.0), (30.0, -45.0, 70.0)
    box = Box(center, size, rot)
    poly = Polyhedron(rotated_box_halfspaces(center, size, rot))
    g = torch.Generator().manual_seed(1)
    o, d = rays_towards(box, 2000, g)
    t_box, aux_box = box.intersect(o, d, T_MIN)
    t_poly, aux_poly = poly.intersect(o, d, T_MIN)
    hit = torch.isfinite(t_box)
    assert bool((hit == torch.isfinite(t_poly)).all()), "box and polyhedron disagree on which rays hit"
    assert hit.float().mean() > 0.3, f"test rays should mostly hit, hit fraction {hit.float().mean():.2f}"
    assert torch.allclose(t_box[hit], t_poly[hit], atol=1e-10), "hit distances differ"
    p = o[hit] + t_box[hit, None] * d[hit]
    n_box, _ = box.surface(p, aux_box[hit])
    n_poly, _ = poly.surface(p, aux_poly[hit])
    assert torch.allclose(n_box, n_poly, atol=1e-10), "normals differ"
    r_box, r_poly = box.bounding_sphere()[1], poly.bounding_sphere()[1]
    assert math.isclose(r_box, r_poly, rel_tol=1e-9), f"bounding radii {r_box} vs {r_poly}"


def test_box_mesh_equals_box():
    vertices, triangles = load_obj(str(SCENES / "cube.obj"))
    assert triangles.shape == (12, 3), f"six quads fan into 12 triangles, got {tuple(triangles.shape)}"
    center, size, rot = (0.5, 1.0, -1.0), (2.0, 1.0, 3.0), (-15.0, 25.0, 60.0)
    box = Box(center, size, rot)
    mesh = Mesh(vertices, triangles, center, size, rot)
    g = torch.Generator().manual_seed(2)
    o, d = rays_towards(box, 2000, g)
    t_box, aux_box = box.intersect(o, d, T_MIN)
    t_mesh, aux_mesh = mesh.intersect(o, d, T_MIN)
    hit = torch.isfinite(t_box) & torch.isfinite(t_mesh)
    disagree = (torch.isfinite(t_box) != torch.isfinite(t_mesh)).float().mean()
    assert disagree < 1e-3, f"box and mesh disagree on hit/miss for {disagree:.2%} of rays"
    assert torch.allclose(t_box[hit], t_mesh[hit], atol=1e-9), "hit distances differ"
    p = o[hit] + t_box[hit, None] * d[hit]
    assert torch.allclose(box.surface(p, aux_box[hit])[0], mesh.surface(p, aux_mesh[hit])[0], atol=1e-9), \
        "normals differ"


# ---------------------------------------------------------------------------------------- rectangle


def test_rectangle_hits_both_sides_with_fixed_normal():
    rect = Rectangle((0.0, 0.0, 10.0), (4.0, 2.0))
    t, _, n, _ = cast(rect, [[1.0, 0.5, 0.0], [1.0, 0.5, 20.0]], [[0.0, 0.0, 1.0], [0.0, 0.0, -1.0]])
    assert close(t, [10.0, 10.0]), f"hit from both sides at distance 10, got {t.tolist()}"
    assert close(n, [[0.0, 0.0, 1.0]] * 2), f"normal is local +z whichever side is hit, got {n.tolist()}"


def test_rectangle_misses():
    rect = Rectangle((0.0, 0.0, 10.0), (4.0, 2.0))
    o = [[2.1, 0.0, 0.0], [0.0, 1.1, 0.0], [0.0, 0.0, 10.0], [0.0, 0.0, 11.0]]
    d = [[0.0, 0.0, 1.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]
    t, _, _, _ = cast(rect, o, d)
    assert torch.isinf(t).all(), f"outside x, outside y, in the plane, behind: all miss, got {t.tolist()}"


def test_rectangle_uv_follows_target_layout():
    # u along local x, v along local y, (0, 0) at the corner (−sx/2, −sy/2): with no rotation the default
    # camera (x right, y down, looking along +z) sees u increase to the right and v downwards, as the rows
    # and columns of an image (and the X, Y of a calibration target).
    rect = Rectangle((1.0, 2.0, 10.0), (4.0, 2.0))
    o = [[-1.0, 1.0, 0.0], [3.0, 1.0, 0.0], [-1.0, 3.0, 0.0], [2.5, 2.5, 0.0]]
    _, _, _, uv = cast(rect, o, [[0.0, 0.0, 1.0]] * 4)
    assert close(uv, [[0.0, 0.0], [4.0, 0.0], [0.0, 2.0], [3.5, 1.5]]), f"uv at corners and inside: {uv.tolist()}"


def test_rotated_rectangle_maps_local_axes():
    # Rz(90°): local x is world +y, local y is world −x; the normal stays +z.
    rect = Rectangle((0.0, 0.0, 10.0), (4.0, 2.0), (0.0, 0.0, 90.0))
    _, _, n, uv = cast(rect, [[-0.5, 1.5, 0.0]], [[0.0, 0.0, 1.0]])
    assert close(uv, [[3.5, 1.5]]), f"local (1.5, 0.5) + size/2, got {uv.tolist()}"
    assert close(n, [[0.0, 0.0, 1.0]]), f"normal {n.tolist()}"
    rect = Rectangle((0.0, 0.0, 10.0), (4.0, 2.0), (90.0, 0.0, 0.0))
    _, _, n, _ = cast(rect, [[0.0, -5.0, 10.0]], [[0.0, 1.0, 0.0]])
    assert close(n, [[0.0, -1.0, 0.0]]), f"Rx(90°) turns local +z to world −y, got {n.tolist()}"


# ----------------------------------------------------------------------------------------- cylinder


def test_cylinder_side_and_caps():
    cyl = Cylinder((0.0, 0.0, 0.0), (0.0, 0.0, 3.0), 1.0, 2.0)  # the axis is normalised
    o = [[-5.0, 0.0, 1.0], [0.0, 0.0, -5.0], [0.5, 0.0, 10.0], [0.0, 0.0, 1.0], [0.0, 0.0, 1.0]]
    d = [[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]
    t, aux, n, _ = cast(cyl, o, d)
    assert close(t, [4.0, 5.0, 8.0, 1.0, 1.0]), f"side, base, top, and from inside to side and top: {t.tolist()}"
    assert aux.tolist() == [0, 1, 2, 0, 2], f"aux side/base/top, got {aux.tolist()}"
    expected = [[-1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]
    assert close(n, expected), f"outward normals, got {n.tolist()}"


def test_cylinder_misses():
    cyl = Cylinder((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), 1.0, 2.0)
    o = [[-5.0, 1.1, 1.0], [-5.0, 0.0, 2.5], [1.5, 0.0, -5.0], [0.0, 0.0, -5.0]]
    d = [[1.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, 0.0, -1.0]]
    t, _, _, _ = cast(cyl, o, d)
    assert torch.isinf(t).all(), f"beside, above, parallel outside, away: all miss, got {t.tolist()}"


def test_tilted_cylinder_along_its_axis():
    axis = torch.tensor([1.0, 1.0, 0.0], dtype=torch.float64) / math.sqrt(2)
    cyl = Cylinder((1.0, 2.0, 3.0), axis.tolist(), 0.5, 2.0)
    o = torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64) - 3 * axis
    t, aux, n, _ = cast(cyl, o.tolist(), axis.tolist())
    assert close(t, [3.0]), f"reaches the base cap after 3 units, got {t.tolist()}"
    assert close(n, [(-axis).tolist()]) and int(aux) == 1, f"base normal −axis, got {n.tolist()}, aux {aux.tolist()}"


# --------------------------------------------------------------------------------------------- cone


def test_cone_side_base_apex():
    cone = Cone((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), 1.0, 2.0)  # radius at height z is 1 − z/2
    o = [[-5.0, 0.0, 1.0], [0.0, 0.0, -5.0], [0.0, 0.0, 10.0], [0.0, 0.0, 0.5]]
    d = [[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]]
    t, aux, n, _ = cast(cone, o, d)
    assert close(t, [4.5, 5.0, 8.0, 0.75]), f"side at radius 0.5, base, apex, from inside: {t.tolist()}"
    assert aux.tolist() == [0, 1, 0, 0], f"aux side/base, got {aux.tolist()}"
    slant = [-1 / math.sqrt(1.25), 0.0, 0.5 / math.sqrt(1.25)]
    expected = [slant, [0.0, 0.0, -1.0], [0.0, 0.0, 1.0], [-slant[0], 0.0, slant[2]]]
    assert close(n, expected), f"outward normals (apex: +axis), got {n.tolist()}"


def test_cone_ignores_the_mirror_nappe():
    cone = Cone((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), 1.0, 2.0)
    # Above the apex the equation x² + y² = k²(h − z)² has a second cone; rays through it must miss.
    t, _, _, _ = cast(cone, [[-5.0, 0.0, 2.5], [-5.0, 0.0, 3.0]], [[1.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    assert torch.isinf(t).all(), f"rays above the apex miss, got {t.tolist()}"


def test_cone_bounding_sphere_is_tight():
    for radius, height in [(1.0, 3.0), (2.0, 1.0)]:
        cone = Cone((0.0, 0.0, 0.0), (0.0, 1.0, 0.0), radius, height)
        center, r = cone.bounding_sphere()
        apex = torch.tensor([0.0, height, 0.0], dtype=torch.float64)
        rim = torch.tensor([radius, 0.0, 0.0], dtype=torch.float64)
        assert float(torch.linalg.vector_norm(apex - center)) <= r + 1e-12, f"apex outside ({radius}, {height})"
        rim_distance = float(torch.linalg.vector_norm(rim - center))
        assert math.isclose(rim_distance, r), f"rim at {rim_distance}, not on the sphere of radius {r}"


# --------------------------------------------------------------------------------------------- mesh


def test_icosahedron_mesh():
    ico = Mesh.from_obj(str(SCENES / "icosahedron.obj"))
    assert ico.num_triangles == 20, f"20 faces, got {ico.num_triangles}"
    _, radius = ico.bounding_sphere()
    assert math.isclose(radius, 1.0, rel_tol=1e-6), f"inscribed in the unit sphere, bounding radius {radius}"
    g = torch.Generator().manual_seed(3)
    o, d = rays_towards(ico, 500, g)
    t, aux = ico.intersect(o, d, T_MIN)
    hit = torch.isfinite(t)
    p = o[hit] + t[hit, None] * d[hit]
    n, _ = ico.surface(p, aux[hit])
    inradius = 0.7946544722917661  # of the regular icosahedron with circumradius 1
    r = torch.linalg.vector_norm(p, dim=-1)
    assert bool(((r > inradius - 1e-6) & (r < 1 + 1e-6)).all()), "hit points between in- and circumsphere"
    assert torch.allclose((p * n).sum(-1), torch.full_like(r, inradius), atol=1e-6), \
        "each hit lies on its face's plane n·p = inradius, with outward n"


def test_mesh_chunking_does_not_change_hits(monkeypatch):
    ico = EXAMPLES["mesh"]()
    g = torch.Generator().manual_seed(4)
    o, d = rays_towards(ico, 300, g)
    t_one, aux_one = ico.intersect(o, d, T_MIN)
    monkeypatch.setattr(mesh_module, "_PAIRS_PER_CHUNK", 300 * 3)  # 3 triangles per chunk
    t_many, aux_many = ico.intersect(o, d, T_MIN)
    assert torch.equal(t_one, t_many) and torch.equal(aux_one, aux_many), "chunked result differs"


def test_obj_loader_formats(tmp_path):
    obj = tmp_path / "quad.obj"
    obj.write_text("# a comment\nv 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0 1.0\nvt 0 0\nvn 0 0 1\n"
                   "g group\nusemtl m\nf 1/1/1 2/1/1 3//1\nf -4 -2 -1  # negative indices\n")
    vertices, triangles = load_obj(str(obj))
    assert vertices.shape == (4, 3), f"4 vertices (the w coordinate ignored), got {tuple(vertices.shape)}"
    assert triangles.tolist() == [[0, 1, 2], [0, 2, 3]], f"triangles {triangles.tolist()}"


@pytest.mark.parametrize("text, message", [
    ("v 0 0 0\nv 1 0\n", ":2: expected 3 coordinates"),
    ("v 0 0 0\nv 1 0 zero\n", ":2: expected numbers"),
    ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 4\n", ":4: vertex index 4 out of range"),
    ("v 0 0 0\nv 1 0 0\nf 1 2\n", ":3: a face needs at least 3 vertices"),
    ("v 0 0 0\nv 1 0 0\nv 0 1 0\n", "no faces"),
])
def test_obj_loader_rejects_malformed_files(tmp_path, text, message):
    obj = tmp_path / "bad.obj"
    obj.write_text(text)
    with pytest.raises(ValueError, match=message):
        load_obj(str(obj))


def test_obj_loader_missing_file(tmp_path):
    with pytest.raises(ValueError, match="cannot read .*nothing.obj"):
        load_obj(str(tmp_path / "nothing.obj"))


# --------------------------------------------------------------------------------------- polyhedron


def test_tetrahedron_hits_and_normals():
    tet = Polyhedron(TETRA)
    o = [[0.2, 0.2, -1.0], [0.1, 0.1, 0.1], [-1.0, 0.2, 0.2], [0.2, 0.2, 2.0]]
    d = [[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, -1.0]]
    t, aux, n, _ = cast(tet, o, d)
    assert close(t[:2], [1.0, 0.7]), f"entry through z = 0; from inside to x + y + z = 1: {t.tolist()}"
    assert math.isinf(t[2]), f"parallel to the x = 0 plane, outside it: miss, got {t.tolist()}"
    assert close(t[3:], [1.4]), f"from above through the slanted face, got {t.tolist()}"
    s = 1 / math.sqrt(3)
    assert close(n[[0, 1, 3]], [[0.0, 0.0, -1.0], [s, s, s], [s, s, s]]), f"normals {n.tolist()}"
    assert aux[[0, 1, 3]].tolist() == [2, 3, 3], f"aux is the plane index, got {aux.tolist()}"


@pytest.mark.parametrize("rows, message", [
    ([[1, 0, 0, 1], [-1, 0, 0, 1], [0, 1, 0, 1], [0, -1, 0, 1]], "unbounded"),   # an infinite square prism
    ([[1, 0, 0, 1], [0, 1, 0, 1], [0, 0, 1, 1], [-1, -1, 0, 5]], "unbounded"),   # open towards −z
    (TETRA[:3] + [[1, 1, 1, -1]], "empty"),
    (TETRA + [[0, 0, 1, 0]], "flat"),
    (TETRA[:3], "at least 4"),
    (TETRA[:3] + [[1, 1, 1]], r"halfspaces\[3\]"),
    (TETRA[:3] + [[0, 0, 0, 1]], "non-zero normal"),
])
def test_polyhedron_rejects_bad_halfspaces(rows, message):
    with pytest.raises(ValueError, match=message):
        Polyhedron(rows)


# ----------------------------------------------------------------------------------- every shape


@pytest.mark.parametrize("name", list(EXAMPLES))
def test_contract_types_and_bounding_sphere(name):
    shape = EXAMPLES[name]()
    g = torch.Generator().manual_seed(5)
    o, d = rays_towards(shape, 1000, g)
    t, aux = shape.intersect(o, d, T_MIN)
    assert t.shape == (1000,) and t.dtype == torch.float64, f"t is (N,) in the rays' dtype, got {t.shape} {t.dtype}"
    assert aux.shape == (1000,) and aux.dtype == torch.long, f"aux is (N,) long, got {aux.shape} {aux.dtype}"
    hit = torch.isfinite(t)
    assert hit.float().mean() > 0.2, f"test rays should often hit, hit fraction {hit.float().mean():.2f}"
    assert bool((t[hit] > T_MIN).all()), "hits lie beyond t_min"
    p = o[hit] + t[hit, None] * d[hit]
    n, uv = shape.surface(p, aux[hit])
    assert n.shape == p.shape and uv.shape == (p.shape[0], 2), f"normal {tuple(n.shape)}, uv {tuple(uv.shape)}"
    assert torch.allclose(torch.linalg.vector_norm(n, dim=-1), torch.ones(len(n), dtype=n.dtype)), "unit normals"
    assert bool(torch.isfinite(uv).all()), "finite uv"
    center, radius = shape.bounding_sphere()
    dist = torch.linalg.vector_norm(p - center, dim=-1)
    assert bool((dist <= radius * (1 + 1e-9)).all()), f"hit at {float(dist.max())} outside bounding radius {radius}"


@pytest.mark.parametrize("name", SOLIDS)
def test_first_hit_from_outside_faces_the_ray(name):
    shape = EXAMPLES[name]()
    g = torch.Generator().manual_seed(6)
    o, d = rays_towards(shape, 1000, g)
    t, aux = shape.intersect(o, d, T_MIN)
    hit = torch.isfinite(t)
    p = o[hit] + t[hit, None] * d[hit]
    n, _ = shape.surface(p, aux[hit])
    assert bool(((n * d[hit]).sum(-1) <= 1e-9).all()), "outward normals face rays entering a convex solid"
    # Started just past the entry point, the ray is inside and leaves through a surface facing along it.
    inside = p + 1e-7 * d[hit]
    t2, aux2 = shape.intersect(inside, d[hit], T_MIN)
    through = torch.isfinite(t2)
    assert through.float().mean() > 0.99, f"{(~through).float().mean():.2%} of entering rays never leave"
    p2 = inside[through] + t2[through, None] * d[hit][through]
    n2, _ = shape.surface(p2, aux2[through])
    assert bool(((n2 * d[hit][through]).sum(-1) >= -1e-9).all()), "exit normals point along the ray"


@pytest.mark.parametrize("name", list(EXAMPLES))
def test_normal_is_perpendicular_to_the_surface(name):
    # Shift each ray sideways by δ: its new hit differs from the old one by a tangent vector, so
    # (p' − p)·n = O(δ²) on smooth patches (and 0 on flat faces) when the normal is right.
    shape = EXAMPLES[name]()
    g = torch.Generator().manual_seed(7)
    o, d = rays_towards(shape, 1000, g)
    t, aux = shape.intersect(o, d, T_MIN)
    p = o + t[:, None] * d
    n, _ = shape.surface(torch.where(torch.isfinite(t)[:, None], p, o), aux)
    delta = 1e-5
    o2 = o + delta * torch.nn.functional.normalize(torch.linalg.cross(d, unit_vectors(1000, g)), dim=-1)
    t2, aux2 = shape.intersect(o2, d, T_MIN)
    same = torch.isfinite(t) & torch.isfinite(t2) & (aux == aux2) & ((n * d).sum(-1).abs() > 0.2)
    assert same.sum() > 100, f"too few usable rays ({int(same.sum())})"
    p2 = o2 + t2[:, None] * d
    off_plane = ((p2 - p)[same] * n[same]).sum(-1).abs()
    worst = float(off_plane.max())
    assert worst < 1e-8, f"normal not perpendicular to the surface: |(p' − p)·n| up to {worst:.2e}"


@pytest.mark.parametrize("name", list(EXAMPLES))
def test_float32_agrees_with_float64(name):
    shape = EXAMPLES[name]()
    g = torch.Generator().manual_seed(8)
    o, d = rays_towards(shape, 1000, g)
    t64, aux64 = shape.intersect(o, d, T_MIN)
    t32, aux32 = shape.intersect(o.float(), d.float(), T_MIN)
    assert t32.dtype == torch.float32, f"float32 rays give float32 t, got {t32.dtype}"
    both = torch.isfinite(t64) & torch.isfinite(t32)
    disagree = (torch.isfinite(t64) != torch.isfinite(t32)).float().mean()
    assert disagree < 0.01, f"hit/miss differs for {disagree:.2%} of rays"
    assert torch.allclose(t32[both].double(), t64[both], rtol=1e-4, atol=1e-4), "t differs beyond float32 precision"
    p = o[both] + t64[both, None] * d[both]
    n64, uv64 = shape.surface(p, aux64[both])
    n32, uv32 = shape.surface(p.float(), aux64[both])
    assert n32.dtype == torch.float32 and uv32.dtype == torch.float32, "surface follows the points' dtype"
    assert torch.allclose(n32.double(), n64, atol=1e-4), "normals differ beyond float32 precision"
    assert torch.allclose(uv32.double(), uv64, atol=1e-4), "uv differ beyond float32 precision"


@pytest.mark.parametrize("name", list(EXAMPLES))
def test_device_follows_inputs_without_host_sync(name):
    # Tensors on the meta device have no values: any .item(), bool() or CPU-tensor mixing would raise.
    shape = EXAMPLES[name]()
    o, d = torch.randn(5, 3, device="meta"), torch.randn(5, 3, device="meta")
    t, aux = shape.intersect(o, d, T_MIN)
    n, uv = shape.surface(o, aux)
    devices = {x.device.type for x in (t, aux, n, uv)}
    assert devices == {"meta"}, f"outputs should stay on the inputs' device, got {devices}"


# ------------------------------------------------------------------------------------ scene files


def test_build_every_shape_from_a_scene_dict():
    sections = [
        {"type": "box", "center": [0, 0, 5], "size": [1, 2, 3], "rotation_deg": [0, 0, 45]},
        {"type": "rectangle", "center": [0, 0, 5], "size": [1, 2]},
        {"type": "cylinder", "center": [0, 0, 5], "axis": [0, 1, 0], "radius": 1, "height": 2},
        {"type": "cone", "center": [0, 0, 5], "axis": [0, 1, 0], "radius": 1, "height": 2},
        {"type": "mesh", "file": "cube.obj", "center": [0, 0, 5], "scale": 2},
        {"type": "mesh", "file": "cube.obj", "center": [0, 0, 5], "scale": [1, 2, 3], "rotation_deg": [10, 0, 0]},
        {"type": "polyhedron", "halfspaces": [[-1, 0, 0, 0], [0, -1, 0, 0], [0, 0, -1, -4], [1, 1, 1, 6]]},
    ]
    for i, section in enumerate(sections):
        shape = build_shape(f"objects[{i}].shape", section, str(SCENES))
        t, _ = shape.intersect(torch.tensor([[0.1, 0.1, 0.0]]), torch.tensor([[0.0, 0.0, 1.0]]), T_MIN)
        assert bool(torch.isfinite(t).all()), f"{section['type']}: the ray along +z hits it, got {t.tolist()}"


@pytest.mark.parametrize("section, field, message", [
    ({"type": "box", "center": [0, 0, 0], "size": [1, -2, 1]}, "size", "positive"),
    ({"type": "rectangle", "center": [0, 0, 0], "size": [1, 0]}, "size", "positive"),
    ({"type": "cylinder", "center": [0, 0, 0], "axis": [0, 0, 0], "radius": 1, "height": 1}, "axis", "non-zero"),
    ({"type": "cone", "center": [0, 0, 0], "axis": [0, 0, 1], "radius": 1, "height": -1}, "height", "positive"),
    ({"type": "sphere", "center": [0, 0, 0], "radius": 0}, "radius", "positive"),
    ({"type": "mesh", "file": "missing.obj"}, "file", "cannot read"),
    ({"type": "mesh", "file": "cube.obj", "scale": [1, 0, 1]}, "scale", "non-zero"),
    ({"type": "mesh", "file": "cube.obj", "scale": "big"}, "scale", "a list of 3 numbers"),
    ({"type": "polyhedron", "halfspaces": [[1, 0, 0, 1], [0, 1, 0, 1], [0, 0, 1, 1]]}, "halfspaces", "at least 4"),
])
def test_build_shape_names_the_bad_field(section, field, message):
    with pytest.raises(SceneError) as err:
        build_shape("objects[0].shape", section, str(SCENES))
    text = str(err.value)
    assert text.startswith(f"objects[0].shape.{field}"), f"message should name objects[0].shape.{field}: {text}"
    assert message in text, f"message should say {message!r}: {text}"


def test_mesh_size_key_fits_bounding_box_like_a_box():
    """The contract gives meshes the box's transform keys: `size` stretches the file's bounding box."""
    import os

    from renderer.shapes import build_shape

    scenes = os.path.join(os.path.dirname(__file__), "..", "..", "renderer", "scenes")
    mesh = build_shape("o.shape", {"type": "mesh", "file": "cube.obj", "center": [1, 2, 5], "size": [2, 1, 3],
                                   "rotation_deg": [0, 0, 0]}, scenes)
    box = build_shape("o.shape", {"type": "box", "center": [1, 2, 5], "size": [2, 1, 3]})
    g = torch.Generator().manual_seed(3)
    o = torch.rand(500, 3, generator=g, dtype=torch.float64) * 4 - 2 + torch.tensor([1.0, 2.0, 0.0], dtype=torch.float64)
    d = torch.nn.functional.normalize(torch.tensor([1.0, 2.0, 5.0], dtype=torch.float64) - o + 0.3 * torch.randn(500, 3, generator=g, dtype=torch.float64), dim=-1)
    t_mesh, _ = mesh.intersect(o, d, 1e-9)
    t_box, _ = box.intersect(o, d, 1e-9)
    assert torch.isfinite(t_box).sum() > 100, "test rays should mostly hit the box"
    assert torch.equal(torch.isfinite(t_mesh), torch.isfinite(t_box)), "mesh with size hits where the box does"
    hit = torch.isfinite(t_box)
    assert torch.allclose(t_mesh[hit], t_box[hit], atol=1e-9), "same hit distances as the equal box"
