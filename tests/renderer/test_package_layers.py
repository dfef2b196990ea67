"""renderer's layers, read from the source with `ast` (nothing is imported; tests/import_graph.py): no import
cycles among its modules, the library never imports the command line, and `renderer` never imports `tiltfit`.

Every import statement counts, at module level or inside a function. Layers, bottom to top:

library      everything not listed below: scene, shapes, cameras, materials, integrator, render, io, the
             Mitsuba bridge, beam tracing, errors (the exceptions every layer raises), ...
front end    cli (`renderer ...`), its back ends (backends: `--backend mitsuba`, `--cluster`) and __main__:
             they may import the library; no library module imports them.

`tiltfit` builds on `renderer`; `renderer` must never import `tiltfit`.
"""
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
from import_graph import ROOT, describe, find_cycle, graph, imports, inside, modules  # noqa: E402

#: The command line and what only it uses.
FRONT_ENDS = ("renderer.cli", "renderer.cli.main", "renderer.cli.backends", "renderer.cli.animate", "renderer.__main__")


def _front_end_imports(graph_: dict, mods: dict) -> list[str]:
    """'file:line imports module' for every library module's import of a front end."""
    return [f"{os.path.relpath(mods[m], ROOT)}:{line} imports {dst}"
            for m, edges in sorted(graph_.items()) if m not in FRONT_ENDS
            for dst, line in edges.items() if dst in FRONT_ENDS]


def _tiltfit_imports(mods: dict) -> list[str]:
    """'file:line' of every import of tiltfit (or one of its modules) in the files `mods` {module: path}."""
    known = {"tiltfit"} | set(modules("tiltfit"))
    return [f"{os.path.relpath(p, ROOT)}:{line}" for m, p in sorted(mods.items())
            for dst, line in imports(m, p, known) if inside(dst, ("tiltfit",))]


def test_the_checks_find_planted_violations(tmp_path):
    planted = {"renderer.scene.model": {"renderer.tracing.render": 3},
               "renderer.tracing.render": {"renderer.tracing.integrator": 5},
               "renderer.tracing.integrator": {"renderer.scene.model": 7}, "camio.files": {}}
    assert find_cycle(planted) == ["renderer.scene.model", "renderer.tracing.render", "renderer.tracing.integrator",
                                   "renderer.scene.model"], "a three-module cycle should be found, in order"
    planted["renderer.tracing.integrator"] = {}
    assert find_cycle(planted) is None, "without the closing import there is no cycle"
    mods = {m: f"{ROOT}/{m.replace('.', '/')}.py" for m in ("renderer.cli.main", "renderer.tracing.render", "camio.files")}
    bad = _front_end_imports({"renderer.cli.main": {"renderer.tracing.render": 1}, "renderer.tracing.render": {"camio.files": 2},
                              "camio.files": {"renderer.cli.main": 40}}, mods)
    assert bad == ["camio/files.py:40 imports renderer.cli.main"], f"a library module importing cli is found: {bad}"
    src = tmp_path / "x.py"
    src.write_text("import numpy\n\ndef f():\n    from tiltfit.calibrate.model import LensCamera\n    import tiltfit\n")
    got = _tiltfit_imports({"renderer.x": str(src)})
    assert [g.rsplit(":", 1)[1] for g in got] == ["4", "5"], f"function-level imports of tiltfit are found: {got}"


def test_renderer_has_no_import_cycle():
    graph_, mods = graph("renderer")
    assert len(graph_) > 40, f"found the renderer modules ({len(graph_)})"
    assert "renderer.mitsuba.intersect" in graph_ and "renderer.cameras.thin_lens" in graph_, "subpackages are read"
    cycle = find_cycle(graph_)
    assert cycle is None, f"import cycle in renderer: {describe(cycle, graph_, mods) if cycle else ''}"


def test_library_never_imports_the_command_line():
    graph_, mods = graph("renderer")
    for name in FRONT_ENDS:
        assert name in mods, f"{name}: listed as a front end here but no such module (update FRONT_ENDS)"
    assert "renderer.cli.backends" in graph_["renderer.cli.main"], "cli dispatches to its back ends (the graph is read)"
    bad = _front_end_imports(graph_, mods)
    assert not bad, "library modules import the command line: " + "; ".join(bad)


def test_renderer_never_imports_tiltfit():
    mods = modules("renderer")
    assert len(mods) > 40, f"found the renderer modules ({len(mods)})"
    bad = _tiltfit_imports(mods)
    assert not bad, "renderer imports tiltfit (tiltfit builds on renderer, never the reverse): " + ", ".join(bad)
