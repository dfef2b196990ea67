"""Inverted prints, mirror images and target files that do not describe the photo (issue 33 §4–5).

The bad inputs are made from real photos with numpy (flip, invert) or from target files with the other dark-cell
parity or their edges swapped; what one photo can decide is in docs/charuco.md ("Inverted prints and mirror
images")."""
import csv
import dataclasses
import os

import numpy as np
import pytest

from camio.files import read_image
from tiltfit.detect.charuco import MIRROR_IMAGE, detect_board
from tiltfit.detect.chessboard import CONTRADICTS, detect, to_gray
from tiltfit.target.layout import CharucoTarget, Target, TargetError, load_target, target_from_dict

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
WEBCAM = os.path.join(ROOT, "tests", "data", "charuco_webcam")
GOPRO = os.path.join(ROOT, "data", "real", "gopro_wide")
BOARD = {"type": "charuco", "dictionary": "DICT_4X4_1000", "squares": [4, 5], "square_mm": 54, "marker_mm": 40.5,
         "inverted": True}


def _published():
    out = {}
    with open(os.path.join(WEBCAM, "published_corners.csv")) as f:
        for r in csv.DictReader(f):
            out.setdefault(r["image"], {})[int(r["corner_id"])] = (float(r["x_px"]), float(r["y_px"]))
    return out


@pytest.fixture(scope="module")
def gopro():
    """A shipped GoPro photo (8 × 6 corners, 9 × 7 cells) as grey linear, its target, and its detection."""
    target = load_target(os.path.join(GOPRO, "target.json"))
    gray = to_gray(read_image(os.path.join(GOPRO, "GOPR0033.jpg")))
    det = detect(gray, target, measure_blur=False)
    assert det.grid_found and det.found.all(), f"the photo itself: {det.message}"
    return gray, target, det


def test_inverted_key_is_read_written_and_checked():
    t = target_from_dict(BOARD, "T.json")
    assert isinstance(t, CharucoTarget) and t.inverted, "inverted: true is kept"
    assert t.to_dict()["inverted"] is True and "inverted" not in dataclasses.replace(t, inverted=False).to_dict(), \
        "written only when true"
    assert not target_from_dict({**BOARD, "inverted": False}, "T.json").inverted, "false"
    for bad in ("yes", 1, None):
        with pytest.raises(TargetError, match=r"^T\.json: inverted: expected true or false"):
            target_from_dict({**BOARD, "inverted": bad}, "T.json")
    with pytest.raises(TargetError, match=r"^T\.json: inverted: expected true or false"):
        target_from_dict({"type": "checkerboard", "x_edges": [0, 1, 2], "y_edges": [0, 1, 2], "inverted": "no"},
                         "T.json")


def test_inverted_charuco_webcam_frames_match_the_published_corners():
    """The white-on-black board read with `inverted`: every published corner found, no wrong id (none further than
    2 px), median distance 0.1–0.5 px (two detectors on a lossy video; not 0, which would be a copy)."""
    target = target_from_dict(BOARD, "T.json")
    errors = []
    for image, published in _published().items():
        det = detect_board(read_image(os.path.join(WEBCAM, image)), target, measure_blur=False)
        assert det.grid_found, f"{image}: {det.message}"
        for k, xy in published.items():
            assert det.found[k], f"{image}: published corner {k} not found"
            errors.append(float(np.hypot(*(det.corners_px[k] - xy))))
    assert max(errors) < 2.0, f"a corner {max(errors):.2f} px from the published one: a wrong id"
    assert 0.1 < np.median(errors) < 0.5, f"median {np.median(errors):.3f} px from the published corners"


def test_inverted_print_without_the_key_says_so_and_the_key_on_a_normal_print_too():
    image = read_image(os.path.join(WEBCAM, "frame_36.png"))
    plain = target_from_dict({**BOARD, "inverted": False}, "T.json")
    det = detect_board(image, plain, measure_blur=False)
    assert not det.grid_found and '"inverted": true' in det.message, f"the hint: {det.message!r}"
    # the same board printed dark on white (the photo's colours inverted) with the key: the hint says remove it
    det = detect_board(1.0 - image, target_from_dict(BOARD, "T.json"), measure_blur=False)
    assert not det.grid_found and "remove the key" in det.message, f"the hint: {det.message!r}"


def test_mirrored_charuco_frame_is_refused_not_labelled():
    """A mirror image of the board (rows read backwards would give every id wrong) is refused."""
    target = target_from_dict(BOARD, "T.json")
    for name in ("frame_36.png", "frame_39.png"):
        image = read_image(os.path.join(WEBCAM, name))
        det = detect_board(np.ascontiguousarray(image[:, ::-1]), target, measure_blur=False)
        assert not det.grid_found and not det.found.any(), f"{name} mirrored: labelled ({det.message})"
        assert det.message.startswith(MIRROR_IMAGE), f"{name} mirrored: {det.message!r}"


def test_charuco_of_another_dictionary_is_named():
    target = target_from_dict({**BOARD, "dictionary": "DICT_6X6_1000"}, "T.json")
    det = detect_board(read_image(os.path.join(WEBCAM, "frame_36.png")), target, measure_blur=False)
    assert not det.grid_found, det.message
    assert "not of the target's dictionary DICT_6X6_1000" in det.message and "DICT_4X4_1000" in det.message, \
        f"should name the dictionaries, not blur: {det.message!r}"
    assert "blurred" not in det.message, det.message


def test_checkerboard_with_the_other_parity_is_refused(gopro):
    gray, target, _ = gopro
    det = detect(gray, dataclasses.replace(target, dark_cell=(1, 0)), measure_blur=False)
    assert not det.grid_found and not det.found.any(), f"labelled with the wrong parity: {det.message}"
    assert det.message.startswith(CONTRADICTS) and "dark_cell" in det.message, det.message


def test_checkerboard_with_inverted_colours_is_refused_and_read_with_the_key(gopro):
    gray, target, normal = gopro
    inverted = gray.max() - gray
    det = detect(inverted, target, measure_blur=False)
    assert not det.grid_found and "inverted colours" in det.message and '"inverted": true' in det.message, \
        det.message
    det = detect(inverted, dataclasses.replace(target, inverted=True), measure_blur=False)
    assert det.grid_found and det.found.all(), f"with the key: {det.message}"
    e = np.hypot(*(det.corners_px - normal.corners_px).T)
    assert e.max() < 0.05, f"with the key the corners move by up to {e.max():.3f} px"
    det = detect(gray, dataclasses.replace(target, inverted=True), measure_blur=False)
    assert not det.grid_found and "remove the key" in det.message, det.message


def test_mirrored_or_transposed_symmetric_board_is_labelled_consistently(gopro):
    """A board of odd × odd uniform cells looks the same mirrored, turned or transposed: nothing in one photo tells
    them apart, so the labels must be a valid view of the file's board (a projective image, orientation kept) and a
    transposition is noted."""
    from tiltfit.files.det import mirrored

    gray, target, normal = gopro
    det = detect(np.ascontiguousarray(gray[:, ::-1]), target, measure_blur=False)
    assert det.grid_found and det.found.all(), det.message
    assert not mirrored(det.corners_px, target.feature_points()), "labelled as seen from behind"
    # the photo's corners, mirrored, are the board's corners under one of its symmetries (the mirrors)
    seen = normal.corners_px.copy()
    seen[:, 0] = gray.shape[1] - 1 - seen[:, 0]
    ny, nx = target.grid_shape
    grid = det.corners_px.reshape(ny, nx, 2)
    best = min(np.hypot(*(g.reshape(-1, 2) - seen).T).max() for g in (grid[:, ::-1], grid[::-1], grid))
    assert best < 0.05, f"the mirrored photo's labels are no symmetry of the board's ({best:.2f} px)"
    swapped = Target(target.y_edges, target.x_edges, target.dark_cell, target.margin)
    det = detect(gray, swapped, measure_blur=False)
    assert det.grid_found and "x_edges and y_edges are swapped" in det.message, det.message


def test_mirrored_even_by_even_board_is_refused():
    """On a board of 8 × 6 cells a mirror image swaps the colours: no placement explains them (a different
    renderer from the detector: tiltfit.experiments.synth's analytic one)."""
    from renderer import Lens, Sensor
    from tiltfit.experiments.synth import look_at_pose, render_view

    board = Target(tuple(np.arange(0, 161, 20.0)), tuple(np.arange(0, 121, 20.0)), (0, 0), 25.0)
    cam = Lens(50.0, 1e5, 1.0, sensor=Sensor(640, 480, 0.012))
    R, T = look_at_pose(board, (40.0, -30.0, -1400.0), roll_deg=10.0)
    v = render_view(board, cam, R, T, noise_sigma=0.004, seed=6)
    assert detect(v.image, board, measure_blur=False).grid_found, "the photo itself"
    det = detect(np.ascontiguousarray(v.image[:, ::-1]), board, measure_blur=False)
    assert not det.grid_found and "mirrored" in det.message and "dark_cell" in det.message, det.message
