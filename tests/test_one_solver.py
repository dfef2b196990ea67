"""One least-squares solver: `tiltfit/solve/` holds the project's Levenberg–Marquardt and Gauss–Newton loops; no
other module of tiltfit/ or renderer/ iterates linear solves of its own.

Read from the source with `ast` (nothing is imported): a `for`/`while` loop (or a comprehension) whose body
calls a linear solve (`torch.linalg.solve`, `cholesky_solve`, `lstsq`, `np.linalg.solve`, ...) is an iterative
solver, and belongs in tiltfit/solve/ unless listed in ALLOWED with the reason.
"""
import ast
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from import_graph import ROOT, modules  # noqa: E402

#: The solver package, where the loops belong.
SOLVER = os.path.join("tiltfit", "solve") + os.sep
#: Files allowed a loop of linear solves outside it, and why.
ALLOWED = {
}
#: Calls that solve a linear system (the attribute name; on torch, torch.linalg, np.linalg, scipy.linalg ...).
SOLVES = {"solve", "cholesky_solve", "lstsq", "solve_triangular", "lu_solve", "solve_ex", "pinv", "inv"}
#: Names a solve call's receiver may end with (torch.linalg.solve, np.linalg.lstsq, torch.cholesky_solve ...).
RECEIVERS = {"linalg", "torch", "np", "numpy", "scipy"}
LOOPS = (ast.For, ast.AsyncFor, ast.While, ast.ListComp, ast.SetComp, ast.DictComp, ast.GeneratorExp)


def _receiver(node: ast.expr) -> str | None:
    """The last name of a call receiver: `torch.linalg` -> "linalg", `np` -> "np"."""
    if isinstance(node, ast.Attribute):
        return node.attr
    if isinstance(node, ast.Name):
        return node.id
    return None


def solve_loops(path: str) -> list[int]:
    """Lines of the loops in the file whose body calls a linear solve."""
    with open(path, encoding="utf-8") as f:
        tree = ast.parse(f.read(), path)
    found = set()
    for loop in ast.walk(tree):
        if not isinstance(loop, LOOPS):
            continue
        for node in ast.walk(loop):
            if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr in SOLVES \
                    and _receiver(node.func.value) in RECEIVERS:
                found.add(loop.lineno)
                break
    return sorted(found)


def _offenders() -> list[str]:
    out = []
    for package in ("tiltfit", "renderer"):
        for path in modules(package).values():
            rel = os.path.relpath(path, ROOT)
            if rel.startswith(SOLVER) or rel in ALLOWED:
                continue
            out += [f"{rel}:{line}" for line in solve_loops(path)]
    return out


def test_the_scan_finds_a_hand_written_solver(tmp_path):
    src = tmp_path / "x.py"
    src.write_text("import torch\n"
                   "def fit(x, lam):\n"
                   "    for _ in range(20):\n"
                   "        A, g = normal(x)\n"
                   "        x = x - torch.linalg.solve(A + lam * torch.eye(3), g)\n"
                   "    return x\n"
                   "def gn(x):\n"
                   "    while True:\n"
                   "        if done(x):\n"
                   "            break\n"
                   "        x = x + np.linalg.lstsq(J(x), -r(x), rcond=None)[0]\n")
    assert solve_loops(str(src)) == [3, 8], "an LM `for` loop and a Gauss–Newton `while` loop are found"
    src.write_text("import torch\n"
                   "def once(A, b):\n"
                   "    return torch.linalg.solve(A, b)\n"
                   "def many(xs):\n"
                   "    return [torch.linalg.norm(x) for x in xs]\n")
    assert solve_loops(str(src)) == [], "a single solve, and a loop without a solve, are not solvers"


def test_allowed_files_exist():
    for rel in ALLOWED:
        assert os.path.exists(os.path.join(ROOT, rel)), f"{rel}: allowed here but gone (drop it from ALLOWED)"
        assert solve_loops(os.path.join(ROOT, rel)), f"{rel}: allowed here but has no solve loop any more " \
                                                     "(drop it from ALLOWED)"


def test_no_second_least_squares_loop():
    bad = _offenders()
    assert not bad, ("loops of linear solves outside tiltfit/solve/ (a second Levenberg–Marquardt or Gauss–Newton: "
                     "use tiltfit.solve.levenberg_marquardt, least_squares or batched_levenberg_marquardt): "
                     + "; ".join(bad))
