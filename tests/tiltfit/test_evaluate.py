"""tiltfit.photometric.profiles: profiles along polylines, metrics, tables and plots, checked against closed forms."""
import csv
import io
import math

import numpy as np
import pytest
import torch

from tiltfit.photometric.profiles import (EvaluationError, average_error, bias, compare_profiles, csv_table, grey_levels,
                              markdown_table, mean_absolute_error, plot_images, plot_profiles, polyline_samples,
                              profile, rmse, save_figure, write_csv, write_markdown)


def ramp(width=13, height=9, a=3.0, b=2.0, c=-0.5):
    """I(x, y) = a + b·x + c·y on pixel centres; bilinear interpolation reproduces it exactly."""
    y, x = np.mgrid[0:height, 0:width].astype(np.float64)
    return a + b * x + c * y


# ------------------------------------------------------------------------------------------- profiles

def test_profile_of_linear_ramp_is_exact():
    img = ramp()
    line = [[0.3, 0.7], [11.9, 7.2]]
    p = profile(img, line, step_px=0.37)
    expected = 3.0 + 2.0 * p.xy_px[:, 0] - 0.5 * p.xy_px[:, 1]
    np.testing.assert_allclose(p.values, expected, atol=1e-12, err_msg="bilinear ramp must be exact")
    length = math.hypot(11.6, 6.5)
    assert p.s_px[0] == 0 and p.s_px[-1] <= length + 1e-9 and length - p.s_px[-1] < 0.37, "samples span the line"
    np.testing.assert_allclose(np.diff(p.s_px), 0.37, atol=1e-12, err_msg="uniform arc-length step")
    np.testing.assert_allclose(p.xy_px[0], line[0], err_msg="first sample at the first vertex")


def test_step_edge_subpixel_positions():
    # Edge through the centre of column 4: that pixel is half covered (0.5), columns left 0, right 1.
    img = np.zeros((5, 9))
    img[:, 4] = 0.5
    img[:, 5:] = 1.0
    p = profile(img, [[0.0, 2.0], [8.0, 2.0]], step_px=0.25)
    expected = np.clip((p.xy_px[:, 0] - 3.0) / 2.0, 0.0, 1.0)  # linear between pixel centres 3 and 5
    np.testing.assert_allclose(p.values, expected, atol=1e-12, err_msg="sub-pixel samples of a step edge")
    crossing = np.interp(0.5, p.values, p.xy_px[:, 0])
    assert abs(crossing - 4.0) < 1e-12, f"the profile crosses half height at the edge (x = 4), got {crossing}"
    assert abs(profile(img, [[3.5, 1.0], [3.5, 3.0]]).values[0] - 0.25) < 1e-12, "half way between centres"


def test_pixel_convention_on_odd_non_square_image():
    # 7 x 5: the last pixel centre is (6, 4); sampling exactly there returns that pixel's value.
    img = np.arange(35, dtype=np.float64).reshape(5, 7)
    p = profile(img, [[6.0, 0.0], [6.0, 4.0]], step_px=1.0)
    np.testing.assert_allclose(p.values, img[:, 6], err_msg="(x, y) = (column, row), (0, 0) a pixel centre")
    q = profile(img, [[0.0, 4.0], [6.0, 4.0]], step_px=1.0)
    np.testing.assert_allclose(q.values, img[4, :], err_msg="bottom row")
    with pytest.raises(EvaluationError, match="outside"):
        profile(img, [[0.0, 0.0], [6.01, 4.0]])


def test_polyline_with_several_segments():
    img = ramp(a=0.0, b=1.0, c=10.0)
    line = [[1.0, 1.0], [5.0, 1.0], [5.0, 4.0], [5.0, 4.0], [2.0, 8.0]]  # includes a repeated vertex
    p = profile(img, line, step_px=1.0)
    assert len(p.s_px) == 13, f"length 4 + 3 + 5 = 12 gives 13 samples, got {len(p.s_px)}"
    np.testing.assert_allclose(p.xy_px[4], [5.0, 1.0], err_msg="corner at s = 4")
    np.testing.assert_allclose(p.xy_px[7], [5.0, 4.0], err_msg="corner at s = 7")
    np.testing.assert_allclose(p.xy_px[12], [2.0, 8.0], atol=1e-12, err_msg="last vertex at s = 12")
    np.testing.assert_allclose(p.xy_px[9], [5.0 - 0.6 * 2, 4.0 + 0.8 * 2], err_msg="on the diagonal segment")
    np.testing.assert_allclose(p.values, p.xy_px[:, 0] + 10 * p.xy_px[:, 1], atol=1e-12)


def test_channels_and_inputs():
    rgb = np.stack([ramp(b=1.0), ramp(b=2.0), ramp(b=3.0)], -1)
    line = [[1.0, 1.0], [10.0, 6.0]]
    for ch in range(3):
        np.testing.assert_allclose(profile(rgb, line, channel=ch).values, profile(rgb[..., ch], line).values)
    luma = profile(rgb, line).values
    expected = 0.299 * profile(rgb, line, channel=0).values + 0.587 * profile(rgb, line, channel=1).values \
        + 0.114 * profile(rgb, line, channel=2).values
    np.testing.assert_allclose(luma, expected, atol=1e-12, err_msg="luma = BT.601 weights")
    np.testing.assert_allclose(profile(torch.from_numpy(rgb).float(), line).values, luma, rtol=1e-6,
                               err_msg="torch tensors are accepted")


def test_grey_levels():
    lin = np.array([[0.0, 1.0], [0.5, 2.0]])
    g = grey_levels(lin)
    np.testing.assert_array_equal(g, [[0, 255], [round(255 * (1.055 * 0.5 ** (1 / 2.4) - 0.055)), 255]])
    u8 = np.array([[0, 17], [200, 255]], dtype=np.uint8)
    np.testing.assert_array_equal(grey_levels(u8), u8, err_msg="uint8 is taken as already encoded")
    assert not np.allclose(grey_levels(lin, quantize=False), np.round(grey_levels(lin, quantize=False)))


# -------------------------------------------------------------------------------------------- metrics

def test_metrics_on_known_arrays():
    a, b = np.array([0.0, 1.0, 2.0, 3.0]), np.ones(4)
    assert mean_absolute_error(a, b) == 1.0, "(1 + 0 + 1 + 2) / 4"
    assert math.isclose(rmse(a, b), math.sqrt(1.5)), "sqrt((1 + 0 + 1 + 4) / 4)"
    assert bias(a, b) == 0.5, "(−1 + 0 + 1 + 2) / 4"
    assert average_error(a, b) == mean_absolute_error(a, b), "the paper's average error is the MAE"
    assert rmse(a, a) == 0.0 and average_error(b, b) == 0.0


def test_compare_profiles_constant_offset():
    rng = np.random.default_rng(1)
    real = rng.integers(20, 200, size=(12, 17, 3)).astype(np.uint8)
    cg = (real.astype(int) + 7).astype(np.uint8)
    lines = {"red": [[2, 1], [2, 10]], "green": [[0, 5], [8, 5], [16, 0]]}
    rows, profiles = compare_profiles(real, cg, lines, step_px=1.0)
    assert [r["line"] for r in rows] == ["red", "green"]
    for r in rows:
        assert math.isclose(r["average_error"], 7.0), f"{r['line']}: offset of 7 grey levels, got {r}"
        assert math.isclose(r["bias"], -7.0) and math.isclose(r["rmse"], 7.0)
    assert rows[0]["n_samples"] == 10 and math.isclose(rows[0]["length_px"], 9.0)
    assert set(profiles) == {"red", "green"}
    same, _ = compare_profiles(real, real, lines)
    assert all(r["average_error"] == 0 for r in same), "an image against itself"


def test_compare_profiles_linear_images_use_grey_levels():
    lin = np.full((6, 8, 3), 0.2)
    rows, _ = compare_profiles(lin, lin * 1.1, {"l": [[0, 0], [7, 5]]})
    expected = grey_levels(np.array([0.22]))[0] - grey_levels(np.array([0.2]))[0]
    assert math.isclose(rows[0]["average_error"], expected), "errors are in 0–255 sRGB grey levels"
    raw, _ = compare_profiles(lin, lin * 1.1, {"l": [[0, 0], [7, 5]]}, to_grey_levels=False)
    assert math.isclose(raw[0]["average_error"], 0.02), "values as given"


# ---------------------------------------------------------------------------------------- bad input

@pytest.mark.parametrize("line, match", [
    ([1.0, 2.0], "K, 2"),
    ([[1.0, 2.0]], "K >= 2"),
    ([[1.0, 2.0, 3.0], [1.0, 2.0, 3.0]], "K, 2"),
    ([[1.0, np.nan], [2.0, 2.0]], "finite"),
    ([[1.0, 1.0], [1.0, 1.0]], "zero length"),
    ([[-0.5, 1.0], [2.0, 2.0]], "outside"),
    ([[1.0, 1.0], [2.0, 9.0]], "outside"),
])
def test_bad_polylines(line, match):
    with pytest.raises(EvaluationError, match=match):
        profile(ramp(), line)


@pytest.mark.parametrize("step", [0, -1.0, float("nan"), float("inf"), "1", True])
def test_bad_step(step):
    with pytest.raises(EvaluationError, match="step_px"):
        profile(ramp(), [[0, 0], [3, 3]], step_px=step)


def test_bad_images_channels_and_pairs():
    line = [[0, 0], [3, 3]]
    with pytest.raises(EvaluationError, match="image"):
        profile(np.zeros(10), line)
    with pytest.raises(EvaluationError, match="image"):
        profile(np.zeros((1, 10)), line)
    with pytest.raises(EvaluationError, match="channel"):
        profile(np.zeros((5, 5, 3)), line, channel=3)
    with pytest.raises(EvaluationError, match="channel"):
        profile(np.zeros((5, 5, 3)), line, channel="red")
    with pytest.raises(EvaluationError, match="channel"):
        profile(np.zeros((5, 5, 2)), line)
    with pytest.raises(EvaluationError, match="differs"):
        compare_profiles(np.zeros((5, 5)), np.zeros((5, 6)), {"l": line})
    with pytest.raises(EvaluationError, match="lines"):
        compare_profiles(np.zeros((5, 5)), np.zeros((5, 5)), [line])
    with pytest.raises(EvaluationError, match="shape"):
        rmse(np.zeros(3), np.zeros(4))
    with pytest.raises(EvaluationError, match="empty"):
        mean_absolute_error([], [])
    with pytest.raises(EvaluationError, match="NaN"):
        bias([np.nan], [0.0])
    with pytest.raises(EvaluationError, match="zero length"):
        polyline_samples([[1, 1], [1, 1]])


# ---------------------------------------------------------------------------------------- tables, plots

ROWS = [{"line": "red", "average_error": 1.23456, "n": 3}, {"line": "gr|een", "average_error": None, "n": 4}]


def test_markdown_and_csv(tmp_path):
    md = markdown_table(ROWS)
    lines = md.splitlines()
    assert lines[0] == "| line | average_error | n |" and lines[1] == "|---|---|---|"
    assert lines[2] == "| red | 1.235 | 3 |" and "gr\\|een" in lines[3], md
    rows = list(csv.DictReader(io.StringIO(csv_table(ROWS))))
    assert rows[0] == {"line": "red", "average_error": "1.23456", "n": "3"} and rows[1]["average_error"] == ""
    text = write_markdown(ROWS, str(tmp_path / "t" / "a.md"), columns=["n", "line"], title="T")
    assert text.startswith("# T\n\n| n | line |") and (tmp_path / "t" / "a.md").read_text() == text
    write_csv(ROWS, str(tmp_path / "a.csv"))
    assert (tmp_path / "a.csv").read_text() == csv_table(ROWS)
    with pytest.raises(EvaluationError):
        markdown_table([])


def test_plots_write_png(tmp_path):
    img = np.clip(ramp(40, 30, a=0.0, b=0.02, c=0.01), 0, 1)
    lines = {"red": [[5, 2], [5, 27]], "green": [[1, 15], [38, 15]]}
    rows, profiles = compare_profiles(img, img * 0.9, lines)
    fig = plot_profiles({"real": profiles["red"][0], "CG": profiles["red"][1]}, title="red line")
    save_figure(fig, str(tmp_path / "p.png"))
    fig2 = plot_images({"real": img, "CG": (img * 200).astype(np.uint8)}, lines, title="x")
    save_figure(fig2, str(tmp_path / "i.png"))
    for name in ("p.png", "i.png"):
        assert (tmp_path / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", f"{name} is a PNG"
