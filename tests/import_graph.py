"""Import graphs of the project's packages, read from the source with `ast` (nothing is imported), for the
layer tests (tests/tiltfit/test_package_layers.py, tests/renderer/test_package_layers.py).

Every import statement counts, at module level or inside a function (a function-level import that only hides
a cycle is still a cycle). Modules are named by their dotted path; a package's __init__ by the package name.
"""
import ast
import os

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def modules(package: str) -> dict[str, str]:
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


def imports(module: str, path: str, known: set) -> list[tuple[str, int]]:
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


def graph(package: str) -> tuple[dict, dict]:
    """({module: {imported module: first line}}, {module: path}) over `package`'s own modules."""
    mods = modules(package)
    graph = {}
    for m, p in mods.items():
        edges = {}
        for dst, line in imports(m, p, set(mods)):
            if dst != m:
                edges.setdefault(dst, line)
        graph[m] = edges
    return graph, mods


def find_cycle(graph: dict) -> list | None:
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


def inside(module: str, names) -> bool:
    return any(module == n or module.startswith(n + ".") for n in names)


def describe(cycle, graph, mods) -> str:
    return " -> ".join(f"{a} ({os.path.relpath(mods[a], ROOT)}:{graph[a][b]})" for a, b in zip(cycle, cycle[1:])) \
        + f" -> {cycle[-1]}"
