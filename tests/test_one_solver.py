"""One least-squares solver: `tiltfit/solve/` holds the project's Levenberg–Marquardt and Gauss–Newton loops; no
other module of tiltfit/ or renderer/ iterates linear solves of its own.

Read from the source with `ast` (nothing is imported): a `for`/`while` loop (or a comprehension) whose body
calls a linear solve (`torch.linalg.solve`, `cholesky_solve`, `lstsq`, `np.linalg.solve`, ...) or solves by hand
(a private `_solve…` helper such as a 2 × 2 Cramer's rule, or a determinant `det = …` computed in the loop) is an
iterative solver, and belongs in tiltfit/solve/ unless listed in ALLOWED with the reason.
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
    "renderer/cameras/distortion.py": "`undistort`: Newton's method on millions of independent 2 × 2 systems (one per "
                                      "pixel) by Cramer's rule (`_solve2`), each pixel leaving once converged; a "
                                      "batched least-squares solver would be far slower, and renders depend on its bits",
    "renderer/mitsuba/sensors.py": "`undistort`: the same Newton steps in Dr.Jit, inside Mitsuba's sensor (torch "
                                   "functions cannot run there); kept step for step with renderer/cameras/distortion.py",
    "tiltfit/detect/blur.py": "the edge fit's start: a scan over six trial blur widths β, at each the two levels of "
                              "a band solved in closed form (2 × 2 normal equations); not an iteration, and the fit "
                              "that follows is tiltfit.solve's batched Levenberg–Marquardt",
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


def _solves(node: ast.AST) -> bool:
    """Whether `node` solves a linear system: a library solve, a private `_solve…` helper, or `det = …`."""
    if isinstance(node, ast.Call):
        f = node.func
        if isinstance(f, ast.Attribute) and f.attr in SOLVES and _receiver(f.value) in RECEIVERS:
            return True
        name = f.attr if isinstance(f, ast.Attribute) else f.id if isinstance(f, ast.Name) else ""
        return name.startswith("_") and "solve" in name
    if isinstance(node, ast.Assign):  # det = a * d - b * c: a 2 × 2 determinant (Cramer's rule)
        v = node.value
        return (any(isinstance(t, ast.Name) and t.id == "det" for t in node.targets) and isinstance(v, ast.BinOp)
                and isinstance(v.op, ast.Sub) and all(isinstance(side, ast.BinOp) and isinstance(side.op, ast.Mult)
                                                      for side in (v.left, v.right)))
    return False


def solve_loops(path: str) -> list[int]:
    """Lines of the loops in the file whose body solves a linear system (`_solves`)."""
    with open(path, encoding="utf-8") as f:
        tree = ast.parse(f.read(), path)
    found = set()
    for loop in ast.walk(tree):
        if isinstance(loop, LOOPS) and any(_solves(node) for node in ast.walk(loop)):
            found.add(loop.lineno)
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
    src.write_text("def newton(x, y):\n"
                   "    for _ in range(20):\n"
                   "        x = x - _solve2(jacobian(x), f(x) - y)\n"
                   "    while bad(x):\n"
                   "        a, b, c, d = jacobian(x)\n"
                   "        det = a * d - b * c\n"
                   "        x = x - (d * r(x) - b) / det\n"
                   "    for path in paths:\n"
                   "        det = detect(path)\n"
                   "    return [solve_lm(p) for p in problems]\n")
    assert solve_loops(str(src)) == [2, 4], "Newton loops with a hand 2 × 2 solve are found; a detection named det and calling the solver are not"
    src.write_text("import torch\n"
                   "def once(A, b):\n"
                   "    return torch.linalg.solve(A, b)\n"
                   "def many(xs):\n"
                   "    return [torch.linalg.norm(x) for x in xs]\n")
    assert solve_loops(str(src)) == [], "a single solve, and a loop without a solve, are not solvers"


def test_allowed_files_exist():
    assert ALLOWED, "the allowed list names the hand-solved Newton loops (an empty list makes this test vacuous)"
    for rel in ALLOWED:
        assert os.path.exists(os.path.join(ROOT, rel)), f"{rel}: allowed here but gone (drop it from ALLOWED)"
        assert solve_loops(os.path.join(ROOT, rel)), f"{rel}: allowed here but has no solve loop any more " \
                                                     "(drop it from ALLOWED)"


def test_no_second_least_squares_loop():
    bad = _offenders()
    assert not bad, ("loops of linear solves outside tiltfit/solve/ (a second Levenberg–Marquardt or Gauss–Newton: "
                     "use tiltfit.solve.levenberg_marquardt, least_squares or batched_levenberg_marquardt): "
                     + "; ".join(bad))
