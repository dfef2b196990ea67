"""The ChArUco detector skips its lattice search when OpenCV's corners, refined and completed, already reach every
corner of the board (`tiltfit.detect.charuco._named_corners`): the corners must then be those the lattice alone
names, and the lattice must still be searched where they do not reach every corner."""
import numpy as np

from tiltfit.detect.charuco import detect_charuco
from tiltfit.experiments.charuco_views import FULL, PARTIAL, TARGET, blurred_renders


def test_skipped_lattice_search_gives_the_corners_the_lattice_names():
    rng = np.random.default_rng(3)
    for view in FULL[:2]:
        for truth, sq, b, img in blurred_renders(view, (0.0, 0.05), 0.003, rng):
            fast = detect_charuco(img, TARGET, measure_blur=False)
            assert fast.found.all(), f"blur {b}: {int(fast.found.sum())} of {TARGET.n_points} corners"
            assert "lattice" not in fast.timings_s, f"blur {b}: the lattice was searched with every corner found"
            alone = detect_charuco(img, TARGET, measure_blur=False, use_opencv=False)
            assert "lattice" in alone.timings_s and alone.found.all(), f"blur {b}: the lattice alone: {alone.message}"
            d = np.hypot(*(fast.corners_px - alone.corners_px).T)
            assert d.max() < 0.01, f"blur {b}: a corner {d.max():.4f} px from where the lattice alone puts it"
            e = np.hypot(*(fast.corners_px - truth.corners_px).T)
            assert np.median(e) < 0.02, f"blur {b}: median error {np.median(e):.4f} px against the rendered corners"


def test_lattice_still_searched_on_a_partial_view():
    rng = np.random.default_rng(4)
    truth, sq, b, img = next(blurred_renders(PARTIAL[0], (0.0,), 0.003, rng))
    det = detect_charuco(img, TARGET, measure_blur=False)
    assert not det.found.all() and "lattice" in det.timings_s, f"partial view: {det.message}, {det.timings_s}"
