"""The target description and `tiltfit target design`: a ChArUco board with non-finite squares is a one-line
target error; options that do not apply to the target type are refused, not ignored."""
from __future__ import annotations

import pytest

from tiltfit.target.layout import TargetError, target_from_dict

CHARUCO = {"type": "charuco", "dictionary": "DICT_5X5_100", "squares": [5, 7], "square_mm": 20.0, "marker_mm": 15.0}


@pytest.mark.parametrize("squares", [[float("inf"), 7], [5, float("nan")], [float("-inf"), 7]])
def test_charuco_squares_not_finite_is_a_one_line_target_error(squares):
    """JSON's Infinity / NaN in `squares` (Python's json reads them) is refused by name, not an OverflowError."""
    with pytest.raises(TargetError) as e:
        target_from_dict({**CHARUCO, "squares": squares}, "t.json")
    assert str(e.value).startswith("t.json: squares:") and "\n" not in str(e.value), f"message {e.value!s}"


# --- tiltfit target design: options that do not apply are refused, not ignored -------------------------------
DESIGN = ["target", "design", "--cols", "5", "--rows", "7", "--square-mm", "20"]


@pytest.mark.parametrize("extra, option", [
    (["--charuco", "DICT_5X5_100", "--inclination-deg", "20"], "--inclination-deg"),
    (["--charuco", "DICT_5X5_100", "--w-mm", "4"], "--w-mm"),
    (["--charuco", "DICT_5X5_100", "--distance-mm", "500"], "--distance-mm"),
    (["--w-mm", "4", "--distance-mm", "500", "--marker-mm", "15"], "--marker-mm"),
])
def test_target_design_refuses_options_that_do_not_apply(tmp_path, capsys, extra, option):
    """A ChArUco board has no design view (uniform squares), and a checkerboard has no markers: an option that
    would change nothing is refused with one line naming it, and nothing is written (it was silently ignored)."""
    from tiltfit.cli.main import main

    out = tmp_path / "t.json"
    rc = main(DESIGN + extra + ["-o", str(out), "-q"])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and err.startswith(f"tiltfit: {option}:") and "\n" not in err, f"rc {rc}, stderr {err!r}"
    assert not out.exists(), "nothing written"


def test_target_design_charuco_writes_the_board(tmp_path, capsys):
    from tiltfit.cli.main import main
    from tiltfit.target.layout import CharucoTarget, load_target

    out = tmp_path / "t.json"
    rc = main(DESIGN + ["--charuco", "DICT_4X4_50", "--marker-mm", "14", "-o", str(out), "-q"])
    assert rc == 0, capsys.readouterr().err
    t = load_target(str(out))
    assert isinstance(t, CharucoTarget) and t.squares == (5, 7) and t.marker_mm == 14.0 \
        and t.square_mm == 20.0 and t.dictionary == "DICT_4X4_50", f"the board asked for: {t.to_dict()}"
