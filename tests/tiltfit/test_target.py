"""Target description, file validation, non-uniform row design and images of the board."""
import json
import math
import re

import numpy as np
import pytest

from tiltfit.target.design import design_target, designed_pose, projected_row_spacing
from tiltfit.target.layout import Target, TargetError, load_target
from tiltfit.target.printable import write_printable
from tiltfit.target.raster import rasterise, render_target, target_texture

W_MM, D_MM = 55.39, 620.0  # the paper's w and a distance near its plane of focus


def _asym_target():
    # 4 × 3 cells, columns 10 mm, rows of growing height; corner cell dark
    return Target((0.0, 10.0, 20.0, 30.0, 40.0), (0.0, 8.0, 18.0, 30.0), (0, 0), 5.0)


# --- structure ---------------------------------------------------------------------------------------------
def test_feature_points_row_by_row():
    t = _asym_target()
    p = t.feature_points()
    assert t.grid_shape == (2, 3) and p.shape == (6, 3), f"expected 2×3 interior corners, got {p.shape}"
    expected = [[10, 8], [20, 8], [30, 8], [10, 18], [20, 18], [30, 18]]
    np.testing.assert_allclose(p[:, :2], expected, err_msg="feature points are not ordered Y outer, X inner")
    assert np.all(p[:, 2] == 0), "feature points must lie in Z = 0"
    assert t.feature_index(2, 1) == 5, "feature_index(i=2, j=1) should be 1 * nx + 2"


def test_cell_colours_follow_dark_cell_parity():
    t = _asym_target()
    c = t.cell_colours()
    assert c[0, 0] and not c[0, 1] and c[1, 1], f"cell (0,0) dark and alternating expected, got\n{c}"
    t2 = Target(t.x_edges, t.y_edges, (1, 0), t.margin)
    assert np.array_equal(t2.cell_colours(), ~c), "dark_cell (1, 0) must swap the colours"
    assert not t.is_dark(-1, 0) and not t.is_dark(0, t.n_rows), "the margin is white"


def test_save_load_round_trip(tmp_path):
    t = _asym_target()
    path = tmp_path / "t.json"
    t.save(str(path))
    assert load_target(str(path)) == t, "a saved target must load back equal"
    data = json.loads(path.read_text())
    assert data["type"] == "checkerboard" and data["units"] == "mm", f"contract keys missing: {data}"


# --- validation --------------------------------------------------------------------------------------------
GOOD = {"type": "checkerboard", "units": "mm", "x_edges": [0, 10, 20], "y_edges": [0, 10, 20], "dark_cell": [0, 0],
        "margin": 25}


@pytest.mark.parametrize("change, field", [
    ({"x_edges": None}, "x_edges"),                      # missing
    ({"x_edges": [0, 10, 5]}, "x_edges"),                # not ascending
    ({"y_edges": [0, 10]}, "y_edges"),                   # no interior corner
    ({"y_edges": "0 10 20"}, "y_edges"),                 # wrong type
    ({"type": "circles"}, "type"),
    ({"units": "inch"}, "units"),
    ({"dark_cell": [0]}, "dark_cell"),
    ({"dark_cell": [0.5, 0]}, "dark_cell"),
    ({"margin": -1}, "margin"),
    ({"x_edge": [0, 1, 2]}, "x_edge"),                    # unknown key (typo)
])
def test_load_target_errors_name_file_and_field(tmp_path, change, field):
    data = dict(GOOD)
    for k, v in change.items():
        if v is None:
            del data[k]
        else:
            data[k] = v
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(data))
    with pytest.raises(TargetError) as e:
        load_target(str(path))
    msg = str(e.value)
    assert str(path) in msg and field in msg, f"message should name the file and {field!r}: {msg}"
    assert "\n" not in msg, f"message should be one line: {msg!r}"


def test_load_target_bad_json_and_missing_file(tmp_path):
    path = tmp_path / "broken.json"
    path.write_text("{\"type\": ")
    with pytest.raises(TargetError, match=r"broken.json:1:\d+: not valid JSON"):
        load_target(str(path))
    with pytest.raises(TargetError, match="no such file"):
        load_target(str(tmp_path / "absent.json"))


# --- design ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("inclination", [0.0, 20.0, 35.0])
def test_design_target_projects_rows_uniformly(inclination):
    t = design_target(9, 8, 20.0, w_mm=W_MM, distance_mm=D_MM, inclination_deg=inclination)
    h = projected_row_spacing(t, W_MM, D_MM, inclination)
    spread = (h.max() - h.min()) / h.mean()
    assert spread < 0.01, f"projected row heights vary by {spread:.2%} (expected < 1 %): {h}"
    rows = np.diff(t.y_edges)
    if inclination > 0:
        assert rows[-1] / rows[0] > 1.1, f"rows further away must be taller on the print: {rows}"


def test_design_target_against_independent_projection():
    """Project the row edges with a plain pinhole (x = w X / Z) from the designed pose, not the design maths."""
    t = design_target(7, 6, square_px=150, pixel_pitch_mm=0.00654, w_mm=W_MM, distance_mm=D_MM,
                      inclination_deg=30)
    R, T = designed_pose(t, D_MM, 30.0)
    X = np.stack([np.full(7, 35.0), np.asarray(t.y_edges), np.zeros(7)], 1) @ R.T + T
    y_px = W_MM * X[:, 1] / X[:, 2] / 0.00654
    steps = np.diff(y_px)
    assert np.allclose(steps, 150, rtol=0.01), f"projected rows should be 150 px apart, got {steps}"
    assert t.n_cols + t.n_rows == 13, "n_cols + n_rows odd: a 180° turn changes the corner colour"


def test_design_target_rejects_impossible_view():
    with pytest.raises(TargetError, match="inclination_deg"):
        design_target(4, 40, 20.0, w_mm=W_MM, distance_mm=200.0, inclination_deg=80)


# --- images ------------------------------------------------------------------------------------------------
def test_rasterise_is_area_exact():
    t = _asym_target()
    img = rasterise(t, (-5.0, 45.0), (-5.0, 35.0), 50, 40)  # 1 mm pixels
    dark_area = sum((t.x_edges[i + 1] - t.x_edges[i]) * (t.y_edges[j + 1] - t.y_edges[j])
                    for j in range(t.n_rows) for i in range(t.n_cols) if t.is_dark(i, j))
    assert math.isclose((1 - img).sum(), dark_area, rel_tol=1e-6), "dark area must be preserved exactly"
    half = rasterise(t, (9.5, 10.5), (0.0, 1.0), 1, 1)  # straddles the first column edge in a dark row
    assert math.isclose(float(half[0, 0]), 0.5, abs_tol=1e-6), f"half-covered pixel should be 0.5: {half}"


def test_render_target_size_and_orientation():
    t = _asym_target()
    dpi = 254.0  # 0.1 mm pixels
    img = render_target(t, dpi)
    assert img.shape == (round((30 + 10) / 0.1), round((40 + 10) / 0.1)), f"unexpected size {img.shape}"
    # centre of cell (0, 0) (dark) is at X = 5, Y = 4 -> pixel (col, row) = ((5 + 5)/0.1, (4 + 5)/0.1)
    assert img[90, 100] == 0.0 and img[90, 200] == 1.0, "row = Y, column = X; cell (0, 0) dark, (1, 0) white"
    assert img[5, 5] == 1.0, "the margin is white"


def test_target_texture_orientation_column_x_row_y():
    t = _asym_target()
    tex = target_texture(t, px_per_mm=4.0, dark=0.1, white=0.9)
    x0, y0, x1, y1 = t.extent_mm
    assert tex.shape == (round((y1 - y0) * 4), round((x1 - x0) * 4), 3), f"unexpected texture size {tex.shape}"
    for i in range(t.n_cols):
        for j in range(t.n_rows):
            X = 0.5 * (t.x_edges[i] + t.x_edges[i + 1])
            Y = 0.5 * (t.y_edges[j] + t.y_edges[j + 1])
            v = tex[int((Y - y0) * 4), int((X - x0) * 4), 0]
            assert math.isclose(v, 0.1 if t.is_dark(i, j) else 0.9, abs_tol=1e-6), f"cell ({i}, {j}) has {v}"


def test_write_printable_true_size(tmp_path):
    t = design_target(5, 4, 20.0, w_mm=W_MM, distance_mm=D_MM, inclination_deg=20)
    png, pdf = tmp_path / "t.png", tmp_path / "t.pdf"
    write_printable(t, str(png), str(pdf), dpi=100)
    from matplotlib.image import imread

    img = imread(str(png))
    x0, y0, x1, y1 = t.extent_mm
    assert abs(img.shape[1] - (x1 - x0) / 25.4 * 100) <= 1, f"PNG width {img.shape[1]} px is not true size at 100 dpi"
    text = pdf.read_bytes().decode("latin-1")
    box = [float(v) for v in re.search(r"/MediaBox\s*\[\s*([\d.\s]+)\]", text).group(1).split()]
    assert math.isclose(box[2] / 72 * 25.4, x1 - x0, rel_tol=1e-3), f"PDF page width {box} is not the board width"
    assert box[3] / 72 * 25.4 > y1 - y0, "the PDF page must hold the board and the scale bar"


# --- `tiltfit target design|print` ---------------------------------------------------------------------------
def test_png_scale_bar_is_labelled_and_the_board_unchanged(tmp_path):
    """The PNG holds the exact rasterised board, the bar, and the caption text below the bar."""
    from matplotlib.image import imread

    from camio.files import linear_to_srgb
    from tiltfit.target.printable import _bar_geometry

    t = design_target(5, 4, 20.0, w_mm=W_MM, distance_mm=D_MM, inclination_deg=20)
    png = tmp_path / "t.png"
    write_printable(t, str(png), None, dpi=200)
    img = imread(str(png))
    img = img if img.ndim == 2 else img[..., 0]  # grey (written in strips) or RGBA
    x0, y0, x1, y1 = t.extent_mm
    board = render_target(t, 200)
    ref = linear_to_srgb(board[:-1])  # the last row may be cut differently where the strip begins
    assert np.abs(img[:ref.shape[0], :ref.shape[1]] - ref).max() < 1.5 / 255, "the board in the PNG is altered"
    bx0, by0, L, th = _bar_geometry(t, 15.0, 50.0)
    px = lambda mm: int(round(mm / 25.4 * 200))  # noqa: E731
    under = img[px(by0 + th - y0 + 1.5):px(by0 + th - y0 + 6.0), px(bx0 - x0):px(bx0 - x0 + L)]
    dark = (under < 0.5).mean()
    assert 0.02 < dark < 0.5, f"no caption text under the scale bar in the PNG (dark fraction {dark:.3f})"


def test_target_cli_design_and_print(tmp_path, capsys):
    from tiltfit.cli.main import main

    out = tmp_path / "t.json"
    rc = main(["target", "design", "--cols", "9", "--rows", "7", "--square-mm", "25", "--w-mm", "4",
               "--distance-mm", "500", "--inclination-deg", "10", "-o", str(out)])
    err = capsys.readouterr().err
    assert rc == 0 and out.is_file(), f"design failed: {err}"
    assert "180" in err, f"an even cols + rows should be noted: {err!r}"
    t = load_target(str(out))
    ref = design_target(9, 7, 25.0, w_mm=4.0, distance_mm=500.0, inclination_deg=10.0)
    assert t == ref, "the command line and design_target disagree"
    rc = main(["target", "print", str(out), "--png", str(tmp_path / "t.png"), "--pdf", str(tmp_path / "t.pdf"),
               "--dpi", "100"])
    assert rc == 0 and (tmp_path / "t.png").is_file() and (tmp_path / "t.pdf").is_file(), capsys.readouterr().err


@pytest.mark.parametrize("argv, where", [
    (["design", "--cols", "1001", "--rows", "1001", "--square-mm", "5", "--w-mm", "4", "--distance-mm", "500"],
     "--cols"),
    (["design", "--cols", "9", "--rows", "7", "--square-mm", "-5", "--w-mm", "4", "--distance-mm", "500"],
     "--square-mm"),
    (["print", "{t}", "--png", "{d}/x.png", "--dpi", "100000"], "dpi"),
    (["print", "{d}/missing.json", "--pdf", "{d}/x.pdf"], "missing.json"),
])
def test_target_cli_errors_are_one_line(tmp_path, capsys, argv, where):
    from tiltfit.cli.main import main

    t = tmp_path / "t.json"
    design_target(5, 4, 20.0, w_mm=W_MM, distance_mm=D_MM).save(str(t))
    argv = [a.format(t=t, d=tmp_path) for a in argv]
    if argv[0] == "design":
        argv += ["-o", str(tmp_path / "out.json")]
    rc = main(["target"] + argv)
    err = capsys.readouterr().err.strip()
    assert rc == 2 and err.startswith("tiltfit: ") and "\n" not in err and where in err, f"rc {rc}: {err!r}"
    assert not (tmp_path / "x.png").exists() and not (tmp_path / "out.json").exists(), "partial output left"


def test_png_written_in_strips_is_the_whole_board_exactly(tmp_path, monkeypatch):
    """Strips of a few rows (many seams) give the same board as one rasterisation of the whole page."""
    import OpenImageIO as oiio

    import tiltfit.target.printable as tt
    from camio.files import linear_to_srgb

    monkeypatch.setattr(tt, "PNG_STRIP_PIXELS", 1 << 12)
    t = design_target(5, 4, 20.0, w_mm=W_MM, distance_mm=D_MM, inclination_deg=20)
    write_printable(t, str(tmp_path / "t.png"), None, dpi=100)
    img = oiio.ImageBuf(str(tmp_path / "t.png")).get_pixels(oiio.UINT8)[..., 0].astype(np.float64) / 255
    ref = linear_to_srgb(render_target(t, 100)[:-1])
    assert img.shape[1] == ref.shape[1] and img.shape[0] > ref.shape[0], f"PNG {img.shape}, board {ref.shape}"
    assert np.abs(img[:ref.shape[0]] - ref).max() < 1.5 / 255, "the strips changed the board"


def test_png_print_memory_does_not_grow_with_the_page(tmp_path, monkeypatch):
    """issue 33 §4: a 0.71 m board at 300 dpi took 10 GB (141 bytes a pixel). Python-side peak memory
    (tracemalloc: numpy's arrays included) of printing a 0.65 × 0.53 m board at 100 and 200 dpi (4.4 and 17.7
    megapixels) with strips of 2^16 pixels: the same few MB for both, under 0.5 byte a pixel of the larger."""
    import tracemalloc

    import tiltfit.target.printable as tt

    monkeypatch.setattr(tt, "PNG_STRIP_PIXELS", 1 << 16)
    from tiltfit.target.layout import target_from_dict

    t = target_from_dict({"type": "checkerboard", "units": "mm", "x_edges": [i * 60.0 for i in range(10)],
                          "y_edges": [i * 60.0 for i in range(8)], "dark_cell": [0, 0], "margin": 25})
    write_printable(t, str(tmp_path / "warm.png"), None, dpi=20)  # fonts and modules loaded outside the count
    peaks, pixels = [], []
    for dpi in (100, 200):
        tracemalloc.start()
        try:
            write_printable(t, str(tmp_path / "t.png"), None, dpi=dpi)
            peaks.append(tracemalloc.get_traced_memory()[1])
        finally:
            tracemalloc.stop()
        x0, y0, x1, y1 = t.extent_mm
        pixels.append((x1 - x0) * (y1 + 15 - y0) * (dpi / 25.4) ** 2)
    assert peaks[1] < 1.5 * peaks[0] + (1 << 20), f"peak {peaks[0] / 1e6:.1f} MB -> {peaks[1] / 1e6:.1f} MB for 4x pixels"
    assert peaks[1] < 0.5 * pixels[1], f"{peaks[1] / pixels[1]:.2f} bytes a pixel at 200 dpi"
