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


def _spy_reads(monkeypatch):
    """The marker reads `detect_charuco` asks OpenCV for: their windows (None: OpenCV's default), in order."""
    from tiltfit.detect import charuco

    reads, read = [], charuco.opencv_corners

    def spy(*args, windows=None, **kw):
        reads.append(windows)
        return read(*args, windows=windows, **kw)

    monkeypatch.setattr(charuco, "opencv_corners", spy)
    return reads


def test_first_marker_read_alone_names_the_webcam_frames_as_the_default_read(monkeypatch):
    """OpenCV's first read (FIRST_READ_WINDOWS, fewer threshold passes than its default) names every corner of the three
    real webcam frames, so its default read is skipped; the corners are those the default read leads to."""
    import os

    from camio.files import read_image
    from tiltfit.detect import charuco
    from tiltfit.target.layout import target_from_dict

    webcam = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "data", "charuco_webcam")
    target = target_from_dict({"type": "charuco", "dictionary": "DICT_4X4_1000", "squares": [4, 5], "square_mm": 54,
                               "marker_mm": 40.5, "inverted": True}, "T.json")
    for name in ("frame_26.png", "frame_36.png", "frame_39.png"):
        image = read_image(os.path.join(webcam, name))
        with monkeypatch.context() as m:
            reads = _spy_reads(m)
            fast = detect_charuco(image, target, measure_blur=False)
        assert reads == [charuco.FIRST_READ_WINDOWS], f"{name}: reads {reads}, the first alone should name every corner"
        with monkeypatch.context() as m:
            m.setattr(charuco, "FIRST_READ_WINDOWS", None)  # OpenCV's default read first
            full = detect_charuco(image, target, measure_blur=False)
        assert fast.found.all() and full.found.all(), f"{name}: {fast.message} / {full.message}"
        d = np.hypot(*(fast.corners_px - full.corners_px).T)
        assert d.max() < 1e-3, f"{name}: a corner {d.max():.4f} px from where the default read puts it"


def test_default_marker_read_still_runs_on_a_partial_view(monkeypatch):
    from tiltfit.detect import charuco

    reads = _spy_reads(monkeypatch)
    truth, sq, b, img = next(blurred_renders(PARTIAL[0], (0.0,), 0.003, np.random.default_rng(4)))
    det = detect_charuco(img, TARGET, measure_blur=False)
    assert reads == [charuco.FIRST_READ_WINDOWS, None], f"partial view: reads {reads}"
    assert det.grid_found and not det.found.all(), det.message


def test_top_within_is_the_percentile_test():
    """`_srgb8` scales the photo when its 99.9th percentile lies outside [DARK_PHOTO, 1]; `_top_within` answers
    that from two counts, and must never say 'within' when np.percentile says otherwise."""
    from tiltfit.detect.charuco import _top_within

    rng = np.random.default_rng(5)
    n = 4000  # the percentile lies between order statistics 3995 and 3996 (the counts look at 3994..3997)
    answered = 0
    for trial in range(400):
        x = rng.uniform(0.0, 0.45, n).astype(np.float32)
        # the top values straddle the limits, exactly at them too
        top = rng.choice(np.array([0.3, 0.5, np.nextafter(np.float32(0.5), 0), 0.7, 1.0, 1.2], np.float32), 8)
        x[rng.choice(n, 8, replace=False)] = top
        p = np.percentile(x, 99.9)
        within = _top_within(x, 0.5, 1.0)
        assert not within or 0.5 <= p <= 1.0, f"trial {trial}: within, but the percentile is {p}"
        s = np.sort(x)
        if 0.5 <= s[3994] and s[3997] <= 1.0:
            assert within, f"trial {trial}: the order statistics around it within, answered no"
        answered += within
    assert 50 < answered < 350, f"{answered} of 400 within: the trials should test both answers"


def _motion_blurred(img, length_px, angle_deg, rng, noise=0.003):
    """`img` smeared along a line of `length_px` at `angle_deg` (a box along it: motion, not a lens), plus noise."""
    import cv2

    n = int(np.ceil(length_px)) | 1
    k = np.zeros((n, n), np.float32)
    k[n // 2, :] = 1.0
    k = cv2.warpAffine(k, cv2.getRotationMatrix2D((n / 2 - 0.5, n / 2 - 0.5), angle_deg, 1.0), (n, n))
    out = cv2.filter2D(img.astype(np.float32), -1, k / k.sum(), borderType=cv2.BORDER_REPLICATE)
    return out + rng.normal(0.0, noise, img.shape).astype(np.float32)


def test_edge_spread_never_calls_sharp_a_view_the_width_pass_calls_blurred():
    """Step 5's decision skips the width pass only where the edges' spread is below `sharp_limit`: on renders whose
    blur reaches the markers' data bits (a disc of 0.15-0.8 square, or a smear of half a square along any
    direction, which a steepest slope over all edges would miss) it must stay above it, with a margin; on a sharp
    render below it."""
    from tiltfit.detect.blur import measure_blur
    from tiltfit.detect.charuco import CANCEL_BITS_BLUR, edge_spread_blur, sharp_limit
    from tiltfit.detect.charuco_lattice import _local_square_px
    from tiltfit.detect.imaging import build_pyramid

    rng = np.random.default_rng(6)
    limit = sharp_limit(TARGET)
    cases = []
    for truth, sq, b, img in blurred_renders(PARTIAL[1], (0.0, 0.02, 0.15, 0.3, 0.8), 0.003, rng):
        corners = np.where(truth.in_image[:, None], truth.corners_px, np.nan)
        if b == 0.02:
            cases += [(f"smear 0.5 square at {a}°", _motion_blurred(img, 0.5 * sq, a, rng), corners, True)
                      for a in (0, 60)]
        else:
            cases.append((f"disc {b} square", img, corners, b >= CANCEL_BITS_BLUR))
    for name, img, corners, blurred in cases:
        levels = build_pyramid(np.asarray(img, np.float32))
        spread = float(np.nanmedian(edge_spread_blur(levels, TARGET, corners)))
        if blurred:
            assert spread > 1.5 * limit, f"{name}: edge spread {spread:.3f} square, limit {limit:.3f}"
        else:
            assert spread < limit, f"{name}: edge spread {spread:.3f} square: a sharp view not called sharp"
            width, _ = measure_blur(img, TARGET, corners, levels=levels, max_passes=1)
            assert np.nanmedian(width / _local_square_px(TARGET, corners)) < CANCEL_BITS_BLUR, name


def test_sharp_webcam_frames_skip_the_width_pass_with_the_same_corners(monkeypatch):
    """Corners alone on the real webcam frames (blur about 0.005 square): no width pass runs, and the corners are
    those the width pass would have left (it decides against the model fit)."""
    import os

    from camio.files import read_image
    from tiltfit.detect import blur, charuco
    from tiltfit.target.layout import target_from_dict

    webcam = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "data", "charuco_webcam")
    target = target_from_dict({"type": "charuco", "dictionary": "DICT_4X4_1000", "squares": [4, 5], "square_mm": 54,
                               "marker_mm": 40.5, "inverted": True}, "T.json")
    for name in ("frame_26.png", "frame_36.png"):
        image = read_image(os.path.join(webcam, name))
        with monkeypatch.context() as m:
            calls = []
            measure = blur.measure_blur
            m.setattr(blur, "measure_blur", lambda *a, **kw: calls.append(kw) or measure(*a, **kw))
            fast = detect_charuco(image, target, measure_blur=False)
        assert calls == [], f"{name}: the width pass ran ({calls})"
        with monkeypatch.context() as m:
            m.setattr(charuco, "edge_spread_blur", lambda levels, t, c: np.full(len(c), np.inf))  # never sharp
            passed = detect_charuco(image, target, measure_blur=False)
        assert "model" not in passed.timings_s, f"{name}: the width pass asked for the model fit"
        assert np.array_equal(fast.corners_px, passed.corners_px), f"{name}: the corners moved"


def test_drop_inconsistent_drops_the_corner_its_neighbours_place_elsewhere():
    """Every corner is placed by the homography of its neighbours within two indices (at least 5, not on one line),
    all corners at once: on a whole view with noise of 0.03 px, a corner moved by half a square is the one dropped at
    tolerance 0.2 square; one moved by a tenth is dropped too at 0.05 (with neighbours that the first one's move
    puts out); a view whose neighbours are too few drops nothing."""
    from tiltfit.detect.charuco import drop_inconsistent

    truth = next(blurred_renders(FULL[0], (0.0,), 0.0, np.random.default_rng(7)))[0]
    rng = np.random.default_rng(8)
    clean = np.where(truth.in_image[:, None], truth.corners_px, np.nan) + rng.normal(0, 0.03, truth.corners_px.shape)
    found = np.nonzero(np.isfinite(clean).all(1))[0]
    far, near = int(found[len(found) // 2]), int(found[len(found) // 4])
    sq = np.nanmedian(np.hypot(*np.diff(clean.reshape(*TARGET.grid_shape, 2), axis=1).reshape(-1, 2).T))
    moved = clean.copy()
    moved[far] += [0.5 * sq, 0.0]
    moved[near] += [0.0, 0.1 * sq]
    for tolerance in (0.2, 0.05):
        c = moved.copy()
        n = drop_inconsistent(c, TARGET, tolerance)
        gone = set(np.nonzero(np.isfinite(moved).all(1) & ~np.isfinite(c).all(1))[0].tolist())
        assert n == len(gone), f"tolerance {tolerance}: {n} counted, {len(gone)} dropped"
        if tolerance == 0.2:
            assert gone == {far}, f"tolerance 0.2: dropped {sorted(gone)}, not [{far}]"
        else:
            assert {far, near} <= gone and len(gone) < 0.2 * len(found), f"tolerance 0.05: dropped {sorted(gone)}"
    assert drop_inconsistent(clean.copy(), TARGET, 0.05) == 0, "nothing moved: nothing dropped"
    few = np.full_like(clean, np.nan)
    few[found[:4]] = clean[found[:4]]
    assert drop_inconsistent(few, TARGET) == 0 and np.isfinite(few).all(1).sum() == 4, "4 corners: nothing to place by"
