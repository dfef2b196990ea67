"""Improved beam tracing: polygon conversion (closed-form areas), regions that tile the screen, the region
image against the ray tracer, reuse across a moving viewpoint, and the `renderer animate` command."""
from __future__ import annotations

import csv
import json

import numpy as np
import pytest
import shapely
import torch

from renderer.beam import BeamTracer, ScreenCamera
from renderer.beam.polygons import solid_faces
from renderer.cli.main import main
from camio.files import read_image
from renderer.core.params import SceneError
from renderer.tracing.render import render
from renderer.scene.file import load_scene
from renderer.shapes import build_shape

SCENE = "renderer/scenes/beam_fig2.json"
SMALL = ["image.width=160", "image.height=120"]


def box(lo, hi, extra=()):
    return {"type": "polyhedron", "halfspaces": [[1, 0, 0, hi[0]], [-1, 0, 0, -lo[0]], [0, 1, 0, hi[1]],
                                                 [0, -1, 0, -lo[1]], [0, 0, 1, hi[2]], [0, 0, -1, -lo[2]],
                                                 *extra]}


@pytest.fixture(scope="module")
def scene():
    return load_scene(SCENE, SMALL)


def regions_cover(regions, width, height):
    """(sum of areas, area of their union, sum of pairwise overlap areas), pixels²."""
    polys = np.array([r.poly for r in regions], dtype=object)
    total = float(shapely.area(polys).sum())
    union = float(shapely.union_all(polys).area)
    tree = shapely.STRtree(polys)
    a, b = tree.query(polys, predicate="intersects")
    keep = a < b
    overlap = float(shapely.area(shapely.intersection(polys[a[keep]], polys[b[keep]])).sum())
    return total, union, overlap


# ------------------------------------------------------------------------------------------ step (1)


@pytest.mark.parametrize("cfg, faces, area", [
    # A 2-cube with a redundant plane x <= 5 and a duplicate of x <= 1: 6 faces, area 24.
    (box((-1, -1, -1), (1, 1, 1), [[1, 0, 0, 5], [2, 0, 0, 2]]), 6, 24.0),
    # Minus a unit corner cube: 3 whole faces, 3 L-shaped faces and 3 inner faces; the area stays 24.
    ({"type": "csg", "op": "difference", "children": [box((-1, -1, -1), (1, 1, 1)), box((0, 0, 0), (2, 2, 2))]},
     9, 24.0),
    # Union of two 2-cubes overlapping in a unit cube: each loses 3 unit squares inside the other.
    ({"type": "csg", "op": "union", "children": [box((-1, -1, -1), (1, 1, 1)), box((0, 0, 0), (2, 2, 2))]},
     12, 42.0),
    # Two unit cubes side by side (a shared plane x = 1): the inner faces vanish, outer faces merge.
    ({"type": "csg", "op": "union", "children": [box((0, 0, 0), (1, 1, 1)), box((1, 0, 0), (2, 1, 1))]}, 6, 10.0),
])
def test_polygons_have_the_closed_form_area_and_no_redundant_faces(cfg, faces, area):
    parts = solid_faces(build_shape("s", cfg))
    got = sum(p[-1].area for p in parts)
    assert len(parts) == faces, f"expected {faces} faces, got {len(parts)}"
    assert abs(got - area) < 1e-9, f"expected total area {area}, got {got}"
    for n, c, o, u, v, poly in parts:
        # Every face polygon lies on the solid's surface with n pointing out: just outside is not inside.
        p = shapely.get_coordinates(shapely.point_on_surface(poly))[0]
        x = o + p[0] * u + p[1] * v
        assert abs(n @ x - c) < 1e-9, "face point off its plane"
        shape = build_shape("s", cfg)
        if hasattr(shape, "contains"):
            inside = shape.contains(torch.tensor(np.stack([x - 1e-6 * n, x + 1e-6 * n])))
            assert inside.tolist() == [True, False], f"normal {n} of a face at {x} does not point out"


# ------------------------------------------------------------------------------------------ regions


def test_regions_tile_the_screen_without_overlap(scene):
    tracer = BeamTracer(scene)
    w, h = scene.image.width, scene.image.height
    base = ScreenCamera.of(scene.camera)
    for k in range(8):  # the shipped animation's path at half its step, nodes reused from frame to frame
        frame = tracer.frame(base.moved(0.175 * k))
        total, union, overlap = regions_cover(frame.regions, w, h)
        assert 20 <= len(frame.regions) <= 150, f"frame {k}: expected a few tens of regions, got {len(frame.regions)}"
        assert abs(total - w * h) <= 1e-9 * w * h, f"frame {k}: region areas sum to {total}, screen is {w * h}"
        assert abs(union - w * h) <= 1e-9 * w * h, f"frame {k}: regions cover {union} of the screen's {w * h}"
        assert overlap <= 1e-9 * w * h, f"frame {k}: regions overlap by {overlap} px²"
    frame = tracer.frame(base)
    sigs = {r.signature for r in frame.regions}
    assert max(len(s) for s in sigs) >= 2, "the scene should produce beams reflected more than once"
    assert any(r.target < 0 for r in frame.regions), "some beam should reach the background"


def border_pixels(labels: np.ndarray) -> np.ndarray:
    """(H, W) bool: pixels whose 3×3 neighbourhood holds more than one region."""
    pad = np.pad(labels, 1, mode="edge")
    border = np.zeros(labels.shape, dtype=bool)
    h, w = labels.shape
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            border |= pad[1 + dy:1 + dy + h, 1 + dx:1 + dx + w] != labels
    return border


@pytest.mark.parametrize("frame_index", [0, 3])
def test_region_image_equals_the_ray_traced_image_away_from_borders(scene, frame_index):
    from renderer.beam.shade import label_pixels

    tracer = BeamTracer(scene)
    cam = ScreenCamera.of(scene.camera).moved(0.35 * frame_index)
    frame = tracer.frame(cam)
    image = tracer.render(frame)
    p = cam.eye
    moved = load_scene(SCENE, SMALL + [f"camera.position={p.tolist()}",
                                       f"camera.look_at={(p + cam.world_from_camera[:, 2]).tolist()}"])
    ref = render(moved, spp=1, sampler="center", dtype=torch.float64).image.numpy()
    labels = label_pixels(frame.regions, cam.width, cam.height)
    away = ~border_pixels(labels)
    same = np.abs(image - ref).max(-1) <= 1e-6 + 1e-4 * np.abs(ref).max(-1)
    assert away.mean() > 0.6, f"too few pixels away from borders ({away.mean():.2f})"
    assert same[away].mean() >= 0.99, f"only {same[away].mean():.4f} of the pixels away from borders match"
    # The comparison can fail: the mirrors' contribution is a large part of the image.
    no_mirror = BeamTracer(load_scene(SCENE, SMALL + ["objects.mirror_left.material.reflect=0",
                                                       "objects.mirror_right.material.reflect=0",
                                                       "objects.mirror_back.material.reflect=0"]))
    flat = no_mirror.render(no_mirror.frame(cam))
    differs = np.abs(flat - ref).max(-1) > 1e-3
    assert differs.mean() > 0.1, f"mirrors change only {differs.mean():.3f} of the image: the test would be weak"


def random_scene(seed: int, width=96, height=72) -> dict:
    """Six random convex polyhedra (random planes inside a box) far enough apart not to interpenetrate,
    some of them CSG unions or differences with a smaller polyhedron, half of them mirrors."""
    rng = np.random.default_rng(seed)

    def solid(center, size):
        rows = [[*n, float(n @ center + size)] for n in np.vstack([np.eye(3), -np.eye(3)])]
        for _ in range(int(rng.integers(3, 7))):
            n = rng.normal(size=3)
            n /= np.linalg.norm(n)
            rows.append([*n, float(n @ center + size * rng.uniform(0.6, 1.0))])
        return {"type": "polyhedron", "halfspaces": rows}

    objects, centers = [], []
    while len(objects) < 6:
        c = rng.uniform([-3, -2, 3], [3, 2, 10])
        if any(np.linalg.norm(c - other) < 2.9 for other in centers):
            continue
        centers.append(c)
        size = rng.uniform(0.4, 0.8)
        shape = solid(c, size)
        if rng.random() < 0.4:
            shape = {"type": "csg", "op": str(rng.choice(["union", "difference"])),
                     "children": [shape, solid(c + rng.uniform(-0.4, 0.4, 3), 0.6 * size)]}
        material = {"color": rng.uniform(0.2, 0.9, 3).tolist()}
        if rng.random() < 0.5:
            material["reflect"] = float(rng.uniform(0.5, 1.0))
        objects.append({"name": f"o{len(objects)}", "shape": shape, "material": material})
    return {"image": {"width": width, "height": height, "spp": 1, "sampler": "center", "max_depth": 3,
                      "background": [0.2, 0.3, 0.4]},
            "camera": {"type": "pinhole", "position": [0, 0, 0], "look_at": [0, 0, 5], "fov_deg": 60},
            "lights": [{"type": "point", "position": [1, -4, 1], "intensity": [30, 30, 30]},
                       {"type": "ambient", "intensity": 0.05}],
            "objects": objects}


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_random_scenes_tile_the_screen_and_match_the_ray_tracer(seed):
    from renderer.beam.shade import label_pixels

    scene = load_scene(random_scene(seed))
    tracer = BeamTracer(scene)
    frame = tracer.frame()
    w, h = scene.image.width, scene.image.height
    total, union, overlap = regions_cover(frame.regions, w, h)
    assert max(abs(total - w * h), abs(union - w * h), overlap) <= 1e-9 * w * h, \
        f"seed {seed}: areas {total}, union {union}, overlap {overlap} for a {w * h} px² screen"
    assert any(r.signature for r in frame.regions), f"seed {seed}: no reflected beam at all"
    image = tracer.render(frame)
    ref = render(scene, spp=1, sampler="center", dtype=torch.float64).image.numpy()
    away = ~border_pixels(label_pixels(frame.regions, w, h))
    same = np.abs(image - ref).max(-1) <= 1e-6 + 1e-4 * np.abs(ref).max(-1)
    assert same[away].mean() >= 0.99, f"seed {seed}: only {same[away].mean():.4f} of the pixels match"


# ------------------------------------------------------------------------------------------ moving viewpoint


def same_regions(a, b, area):
    key = lambda r: (r.signature, r.target, round(r.poly.centroid.x, 6), round(r.poly.centroid.y, 6))  # noqa: E731
    a, b = sorted(a, key=key), sorted(b, key=key)
    if [(r.signature, r.target) for r in a] != [(r.signature, r.target) for r in b]:
        return False
    return all(r.poly.symmetric_difference(s.poly).area <= 1e-9 * area for r, s in zip(a, b))


def test_plane_crossing_triggers_redetermination_and_reuse_equals_scratch(scene):
    base = ScreenCamera.of(scene.camera)
    area = base.width * base.height
    tracer = BeamTracer(scene)
    first = tracer.frame(base.moved(0.0))
    assert first.redetermined, "the first frame determines everything"
    # A small step that crosses no polygon plane, real or mirrored: nothing is re-determined.
    quiet = tracer.frame(base.moved(0.02))
    assert not quiet.redetermined and quiet.crossed == [], f"no plane crossed, got {quiet.crossed}"
    assert quiet.timing.nodes_redetermined == 0 and quiet.timing.nodes_ordered == 0, \
        f"a step crossing nothing re-determined {quiet.timing}"
    scratch = BeamTracer(scene, reuse=False).frame(base.moved(0.02))
    assert same_regions(quiet.regions, scratch.regions, area), "reused regions differ from regions from scratch"
    # Frames 2 -> 3 of the shipped animation cross the floor's front plane z = 0.9 (and the block's top).
    tracer.frame(base.moved(0.70))
    crossing = tracer.frame(base.moved(1.05))
    floor_front = [f.index for f in tracer.faces
                   if scene.objects[f.object_id].name == "floor" and abs(f.n[2] + 1) < 1e-9]
    assert crossing.redetermined, "crossing a polygon plane must re-determine"
    assert set(floor_front) <= set(crossing.crossed), f"floor front face {floor_front} not in {crossing.crossed}"
    assert crossing.timing.nodes_redetermined >= 1, "re-determination should redo step (2), the root node at least"
    scratch = BeamTracer(scene, reuse=False).frame(base.moved(1.05))
    assert same_regions(crossing.regions, scratch.regions, area), "regions after a crossing differ from scratch"
    # Without re-determination a crossing would give wrong regions: stale front-facing sets.
    stale = BeamTracer(scene)
    stale.frame(base.moved(0.70))
    stale.segmenter.crossed = lambda a, b: np.zeros(0, dtype=np.int64)
    for node in stale.segmenter.nodes.values():
        node.eye_sides = (lambda side: (lambda eye, tol: (side, np.zeros_like(side))))(node.side)
    wrong = stale.frame(base.moved(1.05))
    assert not same_regions(wrong.regions, scratch.regions, area), "stale step (2) should change the regions"


# ------------------------------------------------------------------------------------------ command


def test_animate_command_writes_frames_and_table(tmp_path, capsys):
    out = tmp_path / "anim"
    args = ["animate", SCENE, "--method", "beam", "--frames", "4", "-o", str(out), "--set", "image.width=64",
            "--set", "image.height=48", "--quiet"]
    assert main(args) == 0
    rows = list(csv.DictReader(open(out / "frames.csv")))
    assert [r["frame"] for r in rows] == ["0", "1", "2", "3"], f"frames: {rows}"
    assert list(rows[0])[:4] == ["frame", "seconds", "regions", "redetermined"], f"columns {list(rows[0])}"
    assert [r["redetermined"] for r in rows] == ["1", "0", "0", "1"], \
        f"frame 0 and the crossing frame 3 should re-determine: {[r['redetermined'] for r in rows]}"
    assert all(int(r["regions"]) > 10 and float(r["seconds"]) > 0 for r in rows), f"{rows}"
    beam = read_image(str(out / "frame_0003.png"))
    assert beam.shape == (48, 64, 3), f"frame image shape {beam.shape}"
    out2 = tmp_path / "trace"
    assert main(["animate", SCENE, "--method", "trace", "--frames", "4", "-o", str(out2), "--set", "image.width=64",
                 "--set", "image.height=48", "--quiet"]) == 0
    rows = list(csv.DictReader(open(out2 / "frames.csv")))
    assert len(rows) == 4 and rows[0]["regions"] == "" and float(rows[0]["seconds"]) > 0, f"{rows}"
    trace = read_image(str(out2 / "frame_0003.png"))
    assert np.mean(np.abs(trace - beam).max(-1) < 2 / 255) > 0.9, "beam and trace frames should mostly agree"


def test_animate_errors_are_one_line_exit_2(tmp_path, capsys):
    cfg = json.load(open(SCENE))
    cfg["animation"] = {"frames": 2.5, "step": 0.1}
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps(cfg))
    assert main(["animate", str(bad), "-o", str(tmp_path / "o")]) == 2
    assert "animation.frames: expected an integer" in capsys.readouterr().err
    cfg["animation"] = None
    del cfg["animation"]
    bad.write_text(json.dumps(cfg))
    assert main(["animate", str(bad), "-o", str(tmp_path / "o")]) == 2
    assert "--frames: not given" in capsys.readouterr().err
    assert main(["animate", "renderer/scenes/fig6.json", "--frames", "1", "--step", "0.1",
                 "-o", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "beam tracing handles" in err and "\n" == err[-1] and err.count("\n") == 1, f"message: {err!r}"
    with pytest.raises(SceneError, match="animation.step"):
        load_scene(SCENE, ["animation.step=fast"])


def _mirror_box(max_depth: int) -> dict:
    """A camera inside a closed box of lossless mirrors, looking at a diffuse cube."""
    def wall(name, axis, sign):
        hs = []
        for a in range(3):
            n = [0.0, 0.0, 0.0]
            if a == axis:
                n[a] = sign
                hs.append(n[:] + [-1.0])        # the wall's inner face at ±1
                n[a] = -sign
                hs.append(n[:] + [1.1])         # its outer face at ±1.1
            else:
                for s in (1.0, -1.0):
                    m = [0.0, 0.0, 0.0]
                    m[a] = s
                    hs.append(m + [1.1])
        return {"name": name, "shape": {"type": "polyhedron", "halfspaces": hs},
                "material": {"color": [0.9, 0.9, 0.9], "reflect": 1.0, "diffuse": 0.0}}

    walls = [wall(f"wall{a}{'+' if s > 0 else '-'}", a, s) for a in range(3) for s in (1.0, -1.0)]
    cube = {"name": "cube", "shape": {"type": "polyhedron", "halfspaces": [
        [1, 0, 0, 0.2], [-1, 0, 0, 0.2], [0, 1, 0, 0.2], [0, -1, 0, 0.2], [0, 0, 1, 0.7], [0, 0, -1, -0.3]]},
        "material": {"color": [0.8, 0.2, 0.2]}}
    return {"image": {"width": 64, "height": 48, "spp": 1, "sampler": "center", "max_depth": max_depth,
                      "background": [0, 0, 0]},
            "camera": {"type": "pinhole", "position": [0.1, 0.05, -0.5], "look_at": [0, 0, 1], "fov_deg": 60},
            "animation": {"frames": 2, "step": 0.05},
            "lights": [{"type": "point", "position": [0, -0.5, 0], "intensity": [1, 1, 1]},
                       {"type": "ambient", "intensity": [0.1, 0.1, 0.1]}],
            "objects": walls + [cube]}


@pytest.mark.slow
def test_a_box_of_lossless_mirrors_is_refused_not_followed_forever(tmp_path):
    """Inside a box of mirrors that lose no light the beams multiply with every reflection: at max_depth 64 the
    segmentation stops at MAX_BEAMS with one line naming image.max_depth (it ran for hours before); at depth 2
    the same box renders."""
    import os
    import sys

    sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    import fuzz_harness

    deep = tmp_path / "deep.json"
    deep.write_text(json.dumps(_mirror_box(64)))
    rc, err = fuzz_harness.run_command(main, ["animate", deep, "--method", "beam", "-o", tmp_path / "deep"],
                                       timeout_s=300)
    assert rc == 2 and "image.max_depth" in err and len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "deep").exists(), "nothing written"
    shallow = tmp_path / "shallow.json"
    shallow.write_text(json.dumps(_mirror_box(2)))
    rc, err = fuzz_harness.run_command(main, ["animate", shallow, "--method", "beam", "-o", tmp_path / "shallow",
                                              "--quiet"], timeout_s=300)
    assert rc == 0 and len(list((tmp_path / "shallow").glob("frame_*.png"))) == 2, err
