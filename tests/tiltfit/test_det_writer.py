"""DET.json has one writer (`tiltfit.detect.detection.write_det_json`): a Detection's file and a plain detector's
dict (`tiltfit detect`) come out alike, rounded the same way and with the permissions of every other output."""
from __future__ import annotations

import json
import os
import stat

import numpy as np

from tiltfit.cli.detect import _det_dict
from tiltfit.detect.detection import Detection, write_det_json, write_detection_json

CORNERS = [[1.234567, 2.0], [np.nan, np.nan]]
BLUR = [0.123456, np.nan]


def test_both_det_writers_round_alike_with_umask_permissions(tmp_path):
    det = Detection((4, 3), np.array(CORNERS), np.array(BLUR), np.full(2, np.nan), True)
    old = os.umask(0o022)
    try:
        write_detection_json(det, str(tmp_path / "a.json"))
        write_det_json(_det_dict(4, 3, CORNERS, BLUR), str(tmp_path / "b.json"))
    finally:
        os.umask(old)
    for name in ("a.json", "b.json"):
        mode = stat.S_IMODE((tmp_path / name).stat().st_mode)
        assert mode == 0o644, f"{name}: mode {oct(mode)}, expected 0o644 (umask 022), as every other output"
    a, b = (json.loads((tmp_path / n).read_text()) for n in ("a.json", "b.json"))
    assert a["corners_px"] == b["corners_px"] == [[1.2346, 2.0], None], "corners rounded to 1e-4 px by both"
    assert a["blur_px"] == b["blur_px"] == [0.1235, None], "blur rounded to 1e-4 px by both"
