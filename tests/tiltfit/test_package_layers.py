"""tiltfit's layers, read from the source with `ast` (nothing is imported; tests/import_graph.py): no import
cycles, the library never imports the experiments, and tiltfit uses only renderer's public API.

Every import statement counts, at module level or inside a function (a function-level import that only hides
a cycle is still a cycle). Layers, bottom to top:

library      everything not listed below: target, imaging (pyramid, homography), solve (the least-squares
             solvers), blur, detect, model, fit (the problem and its solve), start (the starting camera),
             selection (nested-model tests), calibration (the flow), validate, calibfile, detfile, formats,
             export, opencv_corners, report, evaluate (photo vs rendering profiles), photometric, synth
             (synthetic observations and images: public API, used by tests and benchmarks as much as by the
             experiments), target_cli (`tiltfit target ...`). A new module is library
             unless it is added to EXPERIMENTS.
experiments  tiltfit/experiments/: reproduce (the paper's experiment), scenes (its boxes scene), stability and
             its studies, cluster (studies as Ray tasks): built on the library, may import anything below them.
front end    cli, __main__, __init__: may import every layer; nothing imports them.

`tiltfit` builds on `renderer` through its public API; that `renderer` never imports `tiltfit` is checked
with renderer's layers (tests/renderer/test_package_layers.py).
"""
import ast
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
from import_graph import ROOT  # noqa: E402  (the graph helpers are shared with tests/renderer/test_package_layers.py)
from import_graph import describe as _describe  # noqa: E402
from import_graph import find_cycle as _find_cycle  # noqa: E402
from import_graph import graph as _graph  # noqa: E402
from import_graph import imports as _imports  # noqa: E402
from import_graph import inside as _in  # noqa: E402
from import_graph import modules as _modules  # noqa: E402

#: Experiment modules (a package name covers its submodules).
EXPERIMENTS = ("tiltfit.experiments",)
#: Command-line front ends.
FRONT_ENDS = ("tiltfit", "tiltfit.cli", "tiltfit.__main__") + tuple(f"tiltfit.cli.{name}" for name in (
    "main", "parser", "errors", "detect", "calibrate", "photometric", "report", "export", "target"))


def test_find_cycle_finds_a_planted_cycle():
    graph = {"a": {"b": 1}, "b": {"c": 1}, "c": {"a": 1}, "d": {"a": 1}}
    assert _find_cycle(graph) == ["a", "b", "c", "a"], "a three-module cycle is found and printed in order"
    assert _find_cycle({"a": {"b": 1}, "b": {}, "c": {"a": 1, "b": 1}}) is None, "a diamond is not a cycle"


def test_resolves_relative_and_function_level_imports(tmp_path):
    src = tmp_path / "x.py"
    src.write_text("def f():\n    from .chessboard import build\n    from . import blur\n")
    known = {"tiltfit", "tiltfit.detect", "tiltfit.detect.chessboard", "tiltfit.detect.blur", "tiltfit.detect.x"}
    got = sorted(m for m, _ in _imports("tiltfit.detect.x", str(src), known))
    assert got == ["tiltfit.detect.blur", "tiltfit.detect.chessboard"], \
        f"function-level relative imports resolved, got {got}"
    src.write_text("from .. import reproduce\nfrom ..stability.common import Study\n")
    known |= {"tiltfit.experiments.reproduce", "tiltfit.experiments.stability", "tiltfit.experiments.stability.common",
              "tiltfit.experiments.stability.d"}
    got = sorted(m for m, _ in _imports("tiltfit.experiments.stability.d", str(src), known))
    assert got == ["tiltfit.experiments.reproduce", "tiltfit.experiments.stability.common"], f"two-dot imports resolved, got {got}"


def test_tiltfit_has_no_import_cycle():
    graph, mods = _graph("tiltfit")
    assert len(graph) > 10, f"found the tiltfit modules ({len(graph)})"
    cycle = _find_cycle(graph)
    assert cycle is None, f"import cycle in tiltfit: {_describe(cycle, graph, mods) if cycle else ''}"


def test_library_never_imports_experiments_or_front_ends():
    graph, mods = _graph("tiltfit")
    for name in EXPERIMENTS + FRONT_ENDS:
        assert name in mods, f"{name}: listed as a layer here but no such module (update the lists)"
    bad = [f"{os.path.relpath(mods[m], ROOT)}:{line} imports {dst}"
           for m, edges in graph.items() if not _in(m, EXPERIMENTS) and m not in FRONT_ENDS
           for dst, line in edges.items() if _in(dst, EXPERIMENTS)]
    assert not bad, "library modules import experiments: " + "; ".join(bad)
    bad = [f"{os.path.relpath(mods[m], ROOT)}:{line} imports {dst}"
           for m, edges in graph.items() if m not in FRONT_ENDS
           for dst, line in edges.items() if dst in FRONT_ENDS]
    assert not bad, "modules import the command-line front end: " + "; ".join(bad)


#: `renderer`'s public API, the only renderer modules tiltfit may import: the package itself (`renderer.__all__`:
#: LensCamera, ThinLensCamera, project_pinhole, the rotations, render, load_scene, images ...), the cameras
#: package (`renderer.cameras`: the camera classes and the one camera model) with its modules of shared concepts
#: (distortion, optics: closed forms, sensor: exposure), transforms (poses), params, the scene-file reference
#: (formats), Ray clusters (distributed) and the shape registry. `camio`, below both, is not renderer.
RENDERER_PUBLIC = ("renderer", "renderer.cameras", "renderer.cameras.distortion", "renderer.cameras.optics",
                   "renderer.cameras.sensor", "renderer.core.transforms", "renderer.core.params",
                   "renderer.scene.formats", "renderer.tracing.distributed", "renderer.shapes")


def _renderer_imports(path: str) -> list[tuple[str, str | None, int]]:
    """(renderer module, imported name or None, line) for every import of `renderer` in the file."""
    with open(path, encoding="utf-8") as f:
        tree = ast.parse(f.read(), path)
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [(a.name, None, node.lineno) for a in node.names if _in(a.name, ("renderer",))]
        elif isinstance(node, ast.ImportFrom) and not node.level and _in(node.module or "", ("renderer",)):
            out += [(node.module, a.name, node.lineno) for a in node.names]
    return out


def _private_renderer_uses(path: str) -> list[str]:
    """Imports in the file that reach past renderer's public API (a module not in RENDERER_PUBLIC, or a
    name with a leading underscore)."""
    bad = []
    for module, name, line in _renderer_imports(path):
        # `from renderer import cameras` names a module: judge the module it names.
        target = f"{module}.{name}" if name and f"{module}.{name}" in RENDERER_PUBLIC else module
        if target not in RENDERER_PUBLIC or (name or "").startswith("_") or any(
                p.startswith("_") for p in module.split(".")):
            bad.append(f"{os.path.relpath(path, ROOT)}:{line} {module}{'.' + name if name else ''}")
    return bad


def test_the_public_api_check_finds_private_imports(tmp_path):
    src = tmp_path / "x.py"
    src.write_text("from renderer import LensCamera; from renderer.cameras import optics\nfrom renderer.cameras import project_pinhole\n"
                   "def f():\n    import camio.files\n")
    assert _private_renderer_uses(str(src)) == [], "public names and modules pass"
    src.write_text("from renderer.cameras.thin_lens import ThinLensCamera\nfrom renderer.cameras.optics import _tensors\n"
                   "def f():\n    import renderer.tracing.integrator\n")
    got = _private_renderer_uses(str(src))
    assert len(got) == 3, f"an implementation module, a private name and a private module import are found: {got}"


def test_tiltfit_uses_only_renderers_public_api():
    for module in RENDERER_PUBLIC:
        parts = module.split(".")
        path = os.path.join(ROOT, *parts) + ".py"
        assert os.path.exists(path) or os.path.exists(os.path.join(ROOT, *parts, "__init__.py")), \
            f"{module}: listed as public here but no such module (update RENDERER_PUBLIC)"
    bad = [b for p in _modules("tiltfit").values() for b in _private_renderer_uses(p)]
    assert not bad, "tiltfit reaches past renderer's public API (import from renderer or renderer.cameras): " + \
        "; ".join(bad)
