"""Library messages speak in API terms: no "--flag" in the string constants of tiltfit's library modules.

The library is called from Python as much as from the command line; a message such as "needs --distortion auto"
means nothing to a caller of `calibrate(...)`. The command-line front ends (tiltfit/cli/, __main__.py)
translate the library's names into options where needed (`tiltfit.cli.errors.in_cli_terms`). Read from the source
with `ast`: every string constant (f-string parts included) except docstrings, outside functions named `main`
(a module's own command-line glue: its argparse options) and the places in ALLOWED.
"""
import ast
import os
import re
import sys

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
from import_graph import ROOT, modules  # noqa: E402

#: A command-line option: two dashes and a letter, not inside a word (so "x--y" or "---" do not count).
OPTION = re.compile(r"(?<![\w-])--[a-z]")
#: The command-line front ends.
FRONT_ENDS = tuple(f"tiltfit/cli/{name}.py" for name in (
    "main", "parser", "errors", "detect", "calibrate", "photometric", "report", "export", "target")) + ("tiltfit/__main__.py",)
#: (file, function) whose strings may name options, and why.
ALLOWED = {
    ("tiltfit/files/formats.py", "calibration_reference"): "writes docs/file_formats.md, the page on the command line's files",
    ("tiltfit/files/formats.py", "_target_lines"): "writes docs/file_formats.md, the page on the command line's files",
    ("tiltfit/files/formats.py", "_det_lines"): "writes docs/file_formats.md, the page on the command line's files",
    ("tiltfit/files/formats.py", "_calib_lines"): "writes docs/file_formats.md, the page on the command line's files",
    ("tiltfit/files/formats.py", "_photometric_lines"): "writes docs/file_formats.md, the page on the command line's files",
    ("tiltfit/files/formats.py", "_uncertainty_lines"): "writes docs/file_formats.md, the page on the command line's files",
    ("tiltfit/files/formats.py", "_json_lines"): "writes docs/file_formats.md, the page on the command line's files",
    ("tiltfit/experiments/stability/__init__.py", "write_summary"): "the report states the command that made it",
}


def option_strings(path: str, rel: str) -> list[str]:
    """`file:line: text` of the string constants naming a command-line option (module docstring)."""
    with open(path, encoding="utf-8") as f:
        tree = ast.parse(f.read(), path)
    skip = set()
    for node in ast.walk(tree):
        if isinstance(node, (ast.Module, ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)) and node.body \
                and isinstance(node.body[0], ast.Expr) and isinstance(node.body[0].value, ast.Constant):
            skip.add(id(node.body[0].value))  # docstrings
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and (
                node.name == "main" or (rel, node.name) in ALLOWED):
            skip |= {id(n) for n in ast.walk(node)}
    return [f"{rel}:{n.lineno}: {n.value.strip()[:80]!r}" for n in ast.walk(tree)
            if isinstance(n, ast.Constant) and isinstance(n.value, str) and id(n) not in skip and OPTION.search(n.value)]


def test_the_scan_finds_an_option_in_a_message(tmp_path):
    src = tmp_path / "x.py"
    src.write_text('"""Docstrings may say `tiltfit calibrate --init`."""\n'
                   "def fit(model):\n"
                   "    if model != 'auto':\n"
                   "        raise ValueError(f'{model}: needs --distortion auto')\n"
                   "def main(argv=None):\n"
                   "    ap.add_argument('--quick')\n"
                   "X = 'a---b, x--y, -- alone'\n")
    got = option_strings(str(src), "x.py")
    assert len(got) == 1 and "needs --distortion auto" in got[0] and got[0].startswith("x.py:4:"), \
        f"the f-string message is found, the docstring, main's argparse and non-options are not: {got}"


def test_allowed_places_exist():
    for rel, function in ALLOWED:
        with open(os.path.join(ROOT, rel), encoding="utf-8") as f:
            tree = ast.parse(f.read())
        assert any(isinstance(n, ast.FunctionDef) and n.name == function for n in ast.walk(tree)), \
            f"{rel}: no function {function} any more (drop it from ALLOWED)"


def test_library_messages_name_no_command_line_option():
    bad = []
    for path in modules("tiltfit").values():
        rel = os.path.relpath(path, ROOT).replace(os.sep, "/")
        if rel not in FRONT_ENDS:
            bad += option_strings(path, rel)
    assert not bad, ("library strings name command-line options (say the API's argument or option name; the "
                     "front end translates): " + "; ".join(bad))


def test_the_command_line_translates_api_names_back():
    from tiltfit.cli.errors import in_cli_terms

    msg = "cam.yml: pixel_pitch_mm: not in the file; give it as the pixel_pitch_mm argument"
    assert in_cli_terms(msg) == "cam.yml: pixel_pitch_mm: not in the file; give it as --pixel-pitch-mm", \
        f"the front end names the option: {in_cli_terms(msg)!r}"
