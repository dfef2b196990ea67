"""`--backend mitsuba` on every shipped scene and on every shape, texture, light and camera a scene file allows:
what the exporter maps agrees with our tracer, and what it cannot map is named (renderer/mitsuba/export.py).

The scene list, the names expected from each scene file and the overrides neutralising them are those of
benchmarks/renderer/bench_mitsuba_coverage.py (which records the same comparisons at a larger size). Mitsuba runs in
whichever variant runs here (scalar_rgb where Dr.Jit's LLVM backend cannot). Skipped where mitsuba is not
installed, except the geometry of the plane's stand-in, which needs no Mitsuba.
"""
import importlib.util
import json
from pathlib import Path

import numpy as np
import pytest
import torch

pytestmark = pytest.mark.usefixtures("restore_mitsuba_variant")  # conftest: no variant left behind

ROOT = Path(__file__).resolve().parents[2]
SIDE, SPP = 24, 64  # image size (longer side, pixels) and samples per pixel of the comparisons
MEAN_TOL = 0.02  # |Mitsuba's mean / ours − 1| allowed (sampling noise at this size is about 0.3 %)


def _bench():
    spec = importlib.util.spec_from_file_location("bench_mitsuba_coverage",
                                                  ROOT / "benchmarks" / "renderer" / "bench_mitsuba_coverage.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


bench = _bench()
CASES = dict(bench.cases())


def _mitsuba():
    return pytest.importorskip("mitsuba")


def test_plane_pieces_cover_the_view_without_gaps():
    """The rectangles standing in for an infinite floor seen up to its horizon: the first square holds the
    near hits, and every point of the outermost square (out to `PLANE_REACH` times the camera's height or the
    scene's extent) lies in some rectangle."""
    from renderer.mitsuba.tessellate import PLANE_REACH, plane_pieces
    from renderer.scene.file import load_scene

    scene = load_scene(bench.ISSUE_SCENE, ["camera.look_at=[0, -150, 500]"])  # level camera: horizon in view
    floor = scene.objects[0].shape
    centre, pieces = plane_pieces(scene, floor)
    assert np.allclose(centre, [0, 0, 0]), f"centre {centre}: the camera's foot on the floor expected"
    lo, hi = np.array([p[0] for p in pieces]), np.array([p[1] for p in pieces])
    outer = (np.abs(lo) + hi).max()
    reach = PLANE_REACH * max(150, scene.extent)  # the camera's height, or the scene's extent if larger
    assert reach < outer < 1.02 * reach, f"outer square's half side {outer}, expected just over {reach}"
    assert hi[0].max() < 1e-3 * outer, f"first square {hi[0]} should be near the camera, not reach {outer}"
    rng = np.random.default_rng(0)
    points = np.concatenate([rng.uniform(-outer, outer, (20000, 2)),
                             rng.uniform(-1, 1, (20000, 2)) * hi[0] * 1.5])  # the seams near the camera too
    inside = (np.abs(points[:, None] - lo[None]) <= hi[None] * (1 + 1e-9)).all(-1).any(-1)
    assert inside.all(), f"{(~inside).sum()} points fall between the rectangles, e.g. {points[~inside][:3]}"


@pytest.fixture(scope="module")
def mi():
    mi = _mitsuba()
    from renderer.mitsuba import load_mitsuba

    return load_mitsuba()


@pytest.mark.parametrize("name", sorted(CASES))
def test_scene_maps_or_names_what_it_drops(mi, name):
    """Each shipped scene: the exporter names exactly what the scene file holds that Mitsuba cannot
    reproduce; with those elements neutralised, Mitsuba's mean intensity is ours within 2 %. A scene with
    nothing to name is compared as it is."""
    source = CASES[name]
    cfg = bench.scene_config(source)
    size = bench.small(cfg, SIDE)
    from renderer.mitsuba import to_mitsuba
    from renderer.scene.file import load_scene

    scene = load_scene(source, size, base_dir=None if isinstance(source, str) else str(ROOT))
    dropped = to_mitsuba(scene, SPP)[1]
    expected = bench.expected_not_mapped(cfg)
    assert sorted(dropped) == sorted(expected), f"{name}: named {dropped}, the scene file holds {expected}"
    r = bench.compare(source, size + bench.neutral_overrides(cfg), SPP)
    assert r["dropped"] == [], f"{name}: still dropped after neutralising: {r['dropped']}"
    assert abs(r["rel_diff"]) < MEAN_TOL, (f"{name}: mean intensity Mitsuba {r['mitsuba_mean']:.5f} vs ours "
                                           f"{r['ours_mean']:.5f} ({100 * r['rel_diff']:+.2f} %)")


def test_issue_case_through_the_command_line(mi, tmp_path, capsys):
    """Issue 20: tilted lens, infinite checkered floor, sphere, point light. `renderer render --backend
    mitsuba` gives our mean intensity within 2 % (was 26 % darker: the floor ended under the sphere) and our
    image pixel by pixel (floor cells in place); the one stderr line and the metadata name only the sampler."""
    from renderer import render
    from renderer.cli.main import main
    from camio.files import image_metadata, read_image
    from renderer.scene.file import load_scene

    path = tmp_path / "issue.json"
    path.write_text(json.dumps(bench.ISSUE_SCENE))
    size = ["image.width=36", "image.height=24"]
    out = str(tmp_path / "m.exr")
    rc = main(["render", str(path), "-o", out, "--spp", str(SPP), "--backend", "mitsuba", "--quiet",
               *[a for s in size for a in ("--set", s)]])
    assert rc == 0, f"mitsuba render: exit status {rc}"
    err = capsys.readouterr().err
    assert err.strip().endswith("not mapped: sampler sobol (Mitsuba's independent sampler used)"), f"stderr {err!r}"
    meta = image_metadata(out)
    assert meta.get("not_mapped") == "sampler sobol (Mitsuba's independent sampler used)", f"metadata {meta}"
    theirs = read_image(out)[..., :3]
    ours = render(load_scene(str(path), size), spp=SPP, intersector="torch").image.numpy()
    rel = theirs.mean() / ours.mean() - 1
    assert abs(rel) < MEAN_TOL, f"mean Mitsuba {theirs.mean():.5f} vs ours {ours.mean():.5f} ({100 * rel:+.2f} %)"
    floor_rows = slice(12, None)  # the lower half: floor only, the cells several pixels wide
    diff = np.abs(theirs[floor_rows] - ours[floor_rows]).mean() / ours[floor_rows].mean()
    assert diff < 0.08, f"floor pixels differ by {100 * diff:.1f} % of the mean (cells shifted?)"


def test_cli_names_each_dropped_element(mi, tmp_path, capsys):
    """fig6 (mirrors, glass): the one stderr line and the image metadata name each element the scene file
    holds that Mitsuba cannot reproduce."""
    from renderer.cli.main import main
    from camio.files import image_metadata

    out = str(tmp_path / "f.exr")
    rc = main(["render", "fig6", "-o", out, "--backend", "mitsuba", "--spp", "1", "--quiet",
               "--set", "image.width=8", "--set", "image.height=8"])
    assert rc == 0, f"exit status {rc}"
    line = capsys.readouterr().err.strip()
    meta = image_metadata(out)
    expected = bench.expected_not_mapped(bench.scene_config(CASES["renderer/scenes/fig6.json"]))
    assert len(expected) >= 5, f"fig6 should hold at least five unmappable elements, found {expected}"
    for item in expected:
        assert item in line, f"{item!r} missing from the stderr line {line!r}"
        assert item in meta.get("not_mapped", ""), f"{item!r} missing from the metadata {meta}"


# ------------------------------------------------------------------------------- every shape, textured

def _checker(size):
    return {"type": "checker", "size": size, "colors": [[0.9, 0.8, 0.3], [0.1, 0.3, 0.8]]}


def _textured_scene(texture_file: str) -> dict:
    """Every shape type under a checker of its own cell size, an image texture, a point and an ambient light,
    a background: the texture cells of each shape must land where ours do."""
    return {
        "image": {"width": 32, "height": 24, "spp": 32, "max_depth": 0, "background": [0.2, 0.25, 0.3]},
        "camera": {"type": "pinhole", "position": [0, -1.5, -1], "look_at": [0, 0, 4], "screen_size": [1.2, 0.9]},
        "lights": [{"type": "point", "position": [-2, -4, 0], "intensity": [30, 30, 30]},
                   {"type": "ambient", "intensity": [0.1, 0.1, 0.1]}],
        "objects": [
            {"name": "floor", "shape": {"type": "plane", "point": [0.1, 1, 0.2], "normal": [0, -1, 0]},
             "material": {"texture": _checker(0.37)}},
            {"name": "ball", "shape": {"type": "sphere", "center": [-1.2, 0.3, 4], "radius": 0.7},
             "material": {"texture": _checker(0.25)}},
            {"name": "can", "shape": {"type": "cylinder", "center": [0.3, 1.0, 3.0], "axis": [0.3, -1, 0.4],
                                      "radius": 0.4, "height": 0.9}, "material": {"texture": _checker(0.15)}},
            {"name": "cone", "shape": {"type": "cone", "center": [1.5, 1.0, 4.5], "axis": [0, -1, 0.2],
                                       "radius": 0.5, "height": 1.2}, "material": {"texture": _checker(0.2)}},
            {"name": "box", "shape": {"type": "box", "center": [0.2, 0.2, 5.5], "size": [0.8, 1.2, 0.8],
                                      "rotation_deg": [10, 35, 5]}, "material": {"texture": _checker(0.17)}},
            {"name": "tet", "shape": {"type": "polyhedron", "halfspaces": [
                [1, 1, 1, 4.8196], [-1, -1, 1, 2.6196], [-1, 1, -1, -3.3804], [1, -1, -1, -1.9804]]},
             "material": {"texture": _checker(0.13)}},
            {"name": "ico", "shape": {"type": "mesh", "file": str(ROOT / "renderer" / "scenes" / "icosahedron.obj"),
                                      "center": [-0.4, -0.4, 3.0], "scale": 0.35, "rotation_deg": [20, 10, 0]},
             "material": {"texture": _checker(0.1)}},
            {"name": "notch", "shape": {"type": "csg", "op": "difference", "children": [
                {"type": "polyhedron", "halfspaces": [[1, 0, 0, 2.3], [-1, 0, 0, -1.5], [0, 1, 0, 1.0],
                                                      [0, -1, 0, 0.2], [0, 0, 1, 3.4], [0, 0, -1, -2.6]]},
                {"type": "polyhedron", "halfspaces": [[1, 0, 0, 2.5], [-1, 0, 0, -1.9], [0, 1, 0, 0.2],
                                                      [0, -1, 0, 0.6], [0, 0, 1, 3.0], [0, 0, -1, -2.4]]}]},
             "material": {"texture": _checker(0.12)}},
            {"name": "poster", "shape": {"type": "rectangle", "center": [-1.6, -0.6, 6], "size": [1.6, 1.2],
                                         "rotation_deg": [0, -20, 0]},
             "material": {"texture": {"type": "image", "file": texture_file, "size": [0.8, 0.6]}}},
        ],
    }


CAMERAS = {  # native perspective; pinhole with non-square pixels and orthographic through our plugin
    "pinhole": None,
    "pinhole_nonsquare": {"type": "pinhole", "position": [0, -1.5, -1], "look_at": [0, 0, 4],
                          "screen_size": [1.2, 1.0]},
    "orthographic": {"type": "orthographic", "position": [0, -1.5, -1], "look_at": [0, 0, 4], "screen_size": [6, 4.5]},
}


@pytest.mark.parametrize("camera", sorted(CAMERAS))
def test_every_shape_and_texture_lines_up(mi, tmp_path, camera):
    """All shape types textured, image texture, ambient light, background, under Mitsuba's perspective sensor
    and our plugin (pinhole with non-square pixels, orthographic): nothing named, the mean within 2 %, and
    pixel by pixel far closer to ours than a mirrored image (the texture cells: the close-ups below)."""
    from renderer import render
    from renderer.cli.backends import render_mitsuba
    from camio.files import write_image
    from renderer.scene.file import load_scene

    texture = str(tmp_path / "texture.exr")
    write_image(texture, torch.rand(3, 4, 3, generator=torch.Generator().manual_seed(1)), "linear")
    cfg = _textured_scene(texture)
    if CAMERAS[camera] is not None:
        cfg["camera"] = CAMERAS[camera]
    scene = load_scene(cfg)
    ours = render(scene, intersector="torch").image.numpy()
    result = render_mitsuba(scene, sampler="independent", progress=False)
    theirs = result.image.numpy()
    assert result.not_mapped == (), f"{camera}: not mapped {result.not_mapped}"
    rel = theirs.mean() / ours.mean() - 1
    assert abs(rel) < MEAN_TOL, (f"{camera}: mean Mitsuba {theirs.mean():.5f} vs ours {ours.mean():.5f} "
                                 f"({100 * rel:+.2f} %)")
    diff = np.abs(theirs - ours).mean()
    mirrored = min(np.abs(theirs[::-1] - ours).mean(), np.abs(theirs[:, ::-1] - ours).mean())
    assert diff < 0.5 * mirrored, (f"{camera}: per-pixel difference {diff:.4f} not far below that of a mirrored "
                                   f"image {mirrored:.4f}")


def test_issue_case_in_the_scalar_variant(mi):
    """The issue-20 scene in Mitsuba's scalar_rgb variant (what runs where Dr.Jit's LLVM backend cannot):
    mean intensity within 2 % of ours as well."""
    from renderer import render
    from renderer.cli.backends import render_mitsuba
    from renderer.mitsuba import load_mitsuba
    from renderer.scene.file import load_scene

    scene = load_scene(bench.ISSUE_SCENE, ["image.width=36", "image.height=24"])
    try:
        theirs = render_mitsuba(scene, SPP, "independent", variant="scalar_rgb", progress=False).image.numpy()
        assert mi.variant() == "scalar_rgb", f"variant {mi.variant()}"
    finally:
        load_mitsuba()  # back to the default variant for the other tests
    ours = render(scene, spp=SPP, intersector="torch").image.numpy()
    rel = theirs.mean() / ours.mean() - 1
    assert abs(rel) < MEAN_TOL, (f"scalar_rgb: mean Mitsuba {theirs.mean():.5f} vs ours {ours.mean():.5f} "
                                 f"({100 * rel:+.2f} %)")


CLOSEUPS = {  # one shape filling the view, its checker cells a few pixels wide
    "sphere": {"type": "sphere", "center": [0, 0, 0], "radius": 1},
    "cylinder": {"type": "cylinder", "center": [0, 0.6, 0], "axis": [0.2, -1, 0.3], "radius": 0.7, "height": 1.2},
    "cone": {"type": "cone", "center": [0, 0.6, 0], "axis": [0, -1, 0.2], "radius": 0.8, "height": 1.4},
    "box": {"type": "box", "center": [0, 0, 0], "size": [1.4, 1.2, 1.0], "rotation_deg": [10, 35, 5]},
    "polyhedron": {"type": "polyhedron", "halfspaces": [[1, 1, 1, 1.2], [-1, -1, 1, 1.2], [-1, 1, -1, 1.2],
                                                         [1, -1, -1, 1.2]]},
    "mesh": {"type": "mesh", "file": str(ROOT / "renderer" / "scenes" / "icosahedron.obj"), "scale": 1.1,
             "rotation_deg": [20, 10, 0]},
    "csg": {"type": "csg", "op": "difference", "children": [
        {"type": "polyhedron", "halfspaces": [[1, 0, 0, 1], [-1, 0, 0, 1], [0, 1, 0, 1], [0, -1, 0, 1],
                                              [0, 0, 1, 1], [0, 0, -1, 1]]},
        {"type": "polyhedron", "halfspaces": [[1, 0, 0, 1.2], [-1, 0, 0, 0.1], [0, 1, 0, 0.1], [0, -1, 0, 1.2],
                                              [0, 0, 1, 1.2], [0, 0, -1, 0.3]]}]},
    "rectangle": {"type": "rectangle", "center": [0, 0, 0], "size": [2.2, 1.6], "rotation_deg": [20, 30, 0]},
    "plane": {"type": "plane", "point": [0.1, 0.4, 0.2], "normal": [0, -1, 0.4]},
}


@pytest.mark.parametrize("shape", sorted(CLOSEUPS) + ["image_texture"])
def test_texture_cells_land_where_ours_do(mi, tmp_path, shape):
    """A close-up of each shape under a checker (the rectangle also under an image texture): pixel by pixel,
    Mitsuba's image is far closer to ours than Mitsuba's image with the checker colours swapped (or the
    texture image turned upside down) is; cells shifted by half a cell would be halfway between."""
    from renderer import render
    from renderer.cli.backends import render_mitsuba
    from camio.files import write_image
    from renderer.scene.file import load_scene

    texture = {"type": "checker", "size": 0.25, "colors": [[0.9, 0.8, 0.3], [0.1, 0.3, 0.8]]}
    if shape == "image_texture":
        pixels = torch.rand(4, 5, 3, generator=torch.Generator().manual_seed(2))
        write_image(str(tmp_path / "t.exr"), pixels, "linear")
        write_image(str(tmp_path / "flipped.exr"), pixels.flip(0), "linear")
        texture = {"type": "image", "file": str(tmp_path / "t.exr"), "size": [1.1, 0.8]}
    cfg = {"image": {"width": 32, "height": 32, "spp": 16, "max_depth": 0, "background": [0.2, 0.25, 0.3]},
           "camera": {"type": "pinhole", "position": [0.8, -1.2, -3.5], "look_at": [0, 0, 0], "fov_deg": 40},
           "lights": [{"type": "point", "position": [0.8, -1.2, -3.5], "intensity": [12, 12, 12]},
                      {"type": "ambient", "intensity": [0.1, 0.1, 0.1]}],
           "objects": [{"name": shape, "shape": CLOSEUPS.get(shape, CLOSEUPS["rectangle"]),
                        "material": {"texture": texture}}]}
    ours = render(load_scene(cfg), intersector="torch").image.numpy()
    theirs = render_mitsuba(load_scene(cfg), progress=False).image.numpy()
    if shape == "image_texture":
        texture["file"] = str(tmp_path / "flipped.exr")
    else:
        texture["colors"] = texture["colors"][::-1]
    control = render_mitsuba(load_scene(cfg), progress=False).image.numpy()
    diff, wrong = np.abs(theirs - ours).mean(), np.abs(control - ours).mean()
    assert diff < 0.25 * wrong, f"{shape}: per-pixel difference {diff:.4f}, with the texture wrong {wrong:.4f}"


MATERIALS = {  # through our `renderer_phong` plugin: a Phong highlight, a diffuse weight under ambient light
    "highlight_only": {"diffuse": 0, "specular": 1, "shininess": 10},
    "diffuse_and_highlight": {"diffuse": 0.5, "specular": 0.5, "shininess": 60, "color": [0.8, 0.2, 0.1]},
    "diffuse_weight": {"diffuse": 0.4},
}


@pytest.mark.parametrize("material", sorted(MATERIALS))
def test_phong_and_diffuse_weight_carry_over(mi, material):
    """A sphere before a wall lit from the side and by ambient light: nothing named, and Mitsuba's image is
    ours pixel by pixel (within 3 % of the mean; the highlight alone, or the ambient light taken with the
    diffuse weight, would be off by far more)."""
    from renderer import render
    from renderer.cli.backends import render_mitsuba
    from renderer.scene.file import load_scene

    mat = MATERIALS[material]
    cfg = {"image": {"width": 24, "height": 24, "spp": 32, "max_depth": 0},
           "camera": {"type": "pinhole", "position": [0, 0, 0], "look_at": [0, 0, 4], "fov_deg": 35},
           "lights": [{"type": "point", "position": [1, -1, 0], "intensity": [20, 20, 20]},
                      {"type": "ambient", "intensity": [0.2, 0.2, 0.2]}],
           "objects": [{"name": "ball", "shape": {"type": "sphere", "center": [0, 0, 4], "radius": 1}, "material": mat},
                       {"name": "wall", "shape": {"type": "rectangle", "center": [0, 0, 6], "size": [6, 6]},
                        "material": mat}]}
    scene = load_scene(cfg)
    ours = render(scene, intersector="torch").image.numpy()
    result = render_mitsuba(scene, sampler="independent", progress=False)
    assert result.not_mapped == (), f"{material}: not mapped {result.not_mapped}"
    diff = np.abs(result.image.numpy() - ours).mean() / ours.mean()
    assert diff < 0.03, f"{material}: per-pixel difference {100 * diff:.1f} % of the mean"
