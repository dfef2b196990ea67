"""tiltfit's layers, read from the source with `ast` (nothing is imported): no import cycles, the library never
imports the experiments, and `renderer` never imports `tiltfit`.

Every import statement counts, at module level or inside a function (a function-level import that only hides
a cycle is still a cycle). Layers, bottom to top:

library      everything not listed below: target, imaging (pyramid, homography), blur, detect, model, fit,
             validate, calibfile, detfile, formats, export, opencv_corners, report, evaluate (photo vs
             rendering profiles), photometric, synth (synthetic observations and images: public API, used by
             tests and benchmarks as much as by the experiments), runlog (progress lines), target_cli
             (`tiltfit target ...`). A new module is library unless it is added to EXPERIMENTS.
experiments  reproduce (the paper's experiment), scenes (its boxes scene), stability and its studies
             (tiltfit/stability/): built on the library, may import anything below them.
front end    cli, __main__, __init__: may import every layer; nothing imports them.

`tiltfit` builds on `renderer`; `renderer` must never import `tiltfit`.
"""
import ast
import os

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

#: Experiment modules (a package name covers its submodules).
EXPERIMENTS = ("tiltfit.reproduce", "tiltfit.scenes", "tiltfit.stability")
#: Command-line front ends.
FRONT_ENDS = ("tiltfit", "tiltfit.cli", "tiltfit.__main__")


def _modules(package: str) -> dict[str, str]:
    """{dotted module name: file path} of every .py file of `package` (a package's __init__ is its name)."""
    out = {}
    top = os.path.join(ROOT, package)
    for folder, dirs, files in os.walk(top):
        dirs[:] = sorted(d for d in dirs if d != "__pycache__")
        for name in sorted(files):
            if not name.endswith(".py"):
                continue
            parts = os.path.relpath(os.path.join(folder, name), ROOT)[:-3].split(os.sep)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            out[".".join(parts)] = os.path.join(folder, name)
    return out


def _imports(module: str, path: str, known: set) -> list[tuple[str, int]]:
    """(imported module, line) for every import in the file, module or function level, resolved to `known`
    names: `from .x import y` gives x, and x.y when y is a module too; `import a.b.c` the longest known prefix."""
    with open(path, encoding="utf-8") as f:
        tree = ast.parse(f.read(), path)
    is_package = os.path.basename(path) == "__init__.py"
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                parts = alias.name.split(".")
                for k in range(len(parts), 0, -1):
                    if ".".join(parts[:k]) in known:
                        out.append((".".join(parts[:k]), node.lineno))
                        break
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = module.split(".") if is_package else module.split(".")[:-1]
                base = base[:len(base) - (node.level - 1)]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            subs = [f"{target}.{a.name}" for a in node.names if f"{target}.{a.name}" in known]
            out += [(s, node.lineno) for s in subs]
            if target in known and (node.module or len(subs) < len(node.names)):
                out.append((target, node.lineno))
    return out


def _graph(package: str) -> tuple[dict, dict]:
    """({module: {imported module: first line}}, {module: path}) over `package`'s own modules."""
    mods = _modules(package)
    graph = {}
    for m, p in mods.items():
        edges = {}
        for dst, line in _imports(m, p, set(mods)):
            if dst != m:
                edges.setdefault(dst, line)
        graph[m] = edges
    return graph, mods


def _find_cycle(graph: dict) -> list | None:
    """One import cycle [a, b, ..., a] of the graph, or None (depth-first search, three colours)."""
    colour = dict.fromkeys(graph, 0)
    stack = []

    def visit(m):
        colour[m] = 1
        stack.append(m)
        for n in sorted(graph[m]):
            if colour.get(n, 2) == 1:
                return stack[stack.index(n):] + [n]
            if colour.get(n) == 0:
                found = visit(n)
                if found:
                    return found
        stack.pop()
        colour[m] = 2
        return None

    for m in sorted(graph):
        if colour[m] == 0:
            found = visit(m)
            if found:
                return found
    return None


def _in(module: str, names) -> bool:
    return any(module == n or module.startswith(n + ".") for n in names)


def _describe(cycle, graph, mods) -> str:
    return " -> ".join(f"{a} ({os.path.relpath(mods[a], ROOT)}:{graph[a][b]})" for a, b in zip(cycle, cycle[1:])) \
        + f" -> {cycle[-1]}"


def test_find_cycle_finds_a_planted_cycle():
    graph = {"a": {"b": 1}, "b": {"c": 1}, "c": {"a": 1}, "d": {"a": 1}}
    assert _find_cycle(graph) == ["a", "b", "c", "a"], "a three-module cycle is found and printed in order"
    assert _find_cycle({"a": {"b": 1}, "b": {}, "c": {"a": 1, "b": 1}}) is None, "a diamond is not a cycle"


def test_resolves_relative_and_function_level_imports(tmp_path):
    src = tmp_path / "x.py"
    src.write_text("def f():\n    from .detect import build\n    from . import blur\n")
    known = {"tiltfit", "tiltfit.detect", "tiltfit.blur", "tiltfit.x"}
    got = sorted(m for m, _ in _imports("tiltfit.x", str(src), known))
    assert got == ["tiltfit.blur", "tiltfit.detect"], f"function-level relative imports resolved, got {got}"
    src.write_text("from .. import reproduce\nfrom ..stability.common import Study\n")
    known |= {"tiltfit.reproduce", "tiltfit.stability", "tiltfit.stability.common", "tiltfit.stability.d"}
    got = sorted(m for m, _ in _imports("tiltfit.stability.d", str(src), known))
    assert got == ["tiltfit.reproduce", "tiltfit.stability.common"], f"two-dot imports resolved, got {got}"


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


def test_renderer_never_imports_tiltfit():
    mods = _modules("renderer")
    assert len(mods) > 10, f"found the renderer modules ({len(mods)})"
    bad = [f"{os.path.relpath(p, ROOT)}:{line}" for m, p in mods.items()
           for dst, line in _imports(m, p, {"tiltfit"} | set(_modules("tiltfit"))) if _in(dst, ("tiltfit",))]
    assert not bad, "renderer imports tiltfit (tiltfit builds on renderer, never the reverse): " + ", ".join(bad)


#: `renderer`'s public API, the only renderer modules tiltfit may import: the package itself (`renderer.__all__`:
#: LensCamera, ThinLensCamera, project_pinhole, the rotations, render, load_scene, images ...), the cameras
#: package (`renderer.cameras`: the camera classes and the one camera model), and the modules of shared
#: concepts: distortion, optics (closed forms), sensor (exposure), transforms (poses), io, validation, params,
#: formats, distributed, shapes (the registry), cli (the command-line helpers both front ends share).
RENDERER_PUBLIC = ("renderer", "renderer.cameras", "renderer.cameras.distortion", "renderer.optics",
                   "renderer.sensor", "renderer.transforms", "renderer.io", "renderer.validation", "renderer.params",
                   "renderer.formats", "renderer.distributed", "renderer.shapes", "renderer.cli")


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
    src.write_text("from renderer import LensCamera, optics\nfrom renderer.cameras import project_pinhole\n"
                   "def f():\n    import renderer.io\n")
    assert _private_renderer_uses(str(src)) == [], "public names and modules pass"
    src.write_text("from renderer.cameras.thin_lens import ThinLensCamera\nfrom renderer.optics import _tensors\n"
                   "def f():\n    import renderer.integrator\n")
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
