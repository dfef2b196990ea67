"""The point-symmetry refinement's shortcuts (`tiltfit.detect.refine`) give what the plain computation gives, bit
for bit: the interpolant on each corner's box of samples against the whole patch, and the patch smoothing with its
Gaussian taps made once against kornia's `gaussian_blur2d`."""
import numpy as np
import pytest
import torch

from tiltfit.detect import refine


def _junctions(rng, n=6, size=(200, 260)):
    """A linear image of n blurred X-junctions (turned, with unequal levels and noise) and their centres (n, 2)."""
    import cv2

    H, W = size
    img = np.full(size, 0.4, np.float32)
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float64)
    centres = np.c_[rng.uniform(30, W - 30, n), rng.uniform(30, H - 30, n)]
    centres = centres[np.argsort(centres[:, 0])]
    keep = [c for i, c in enumerate(centres) if all(np.hypot(*(c - d)) > 45 for d in centres[:i])]
    centres = np.array(keep)
    for (cx, cy), a in zip(centres, rng.uniform(0, np.pi, len(centres))):
        u = (xx - cx) * np.cos(a) + (yy - cy) * np.sin(a)
        v = -(xx - cx) * np.sin(a) + (yy - cy) * np.cos(a)
        near = np.hypot(xx - cx, yy - cy) < 22
        img[near] = np.where(u[near] * v[near] > 0, 0.8, 0.1)
    img = cv2.GaussianBlur(img, (0, 0), 1.2)
    return img + rng.normal(0, 0.004, img.shape).astype(np.float32), centres


@pytest.mark.parametrize("start_off_px, radius_px", [(0.7, 12.0), (6.0, 12.0), (9.0, 20.0)])
def test_box_of_samples_gives_the_whole_patch_result(monkeypatch, start_off_px, radius_px):
    """Each corner's samples p ± v are interpolated on the box around p alone while that box lies in the patch
    (`refine._box_fits`), else on the whole patch with indices clamped: the positions, asymmetries and flags must be
    those of the whole patch at every step, to the bit, for starts near the corner (the box alone) and 6 or 9 px
    away (some corners wander beyond their box's room and the whole patch takes over)."""
    rng = np.random.default_rng(11)
    img, centres = _junctions(rng)
    turn = rng.uniform(0, 2 * np.pi, len(centres))
    starts = centres + start_off_px * np.c_[np.cos(turn), np.sin(turn)]
    radius = np.full(len(centres), radius_px)
    calls = []
    fits = refine._box_fits
    monkeypatch.setattr(refine, "_box_fits", lambda *a: calls.append(fits(*a)) or calls[-1])
    got = refine.refine_symmetric(img, starts, radius)
    monkeypatch.setattr(refine, "_box_fits", lambda *a: False)
    want = refine.refine_symmetric(img, starts, radius)
    for name, g, w in zip(("positions", "asymmetries", "flags"), got, want):
        assert np.array_equal(g, w), f"start {start_off_px} px off: the {name} differ from the whole patch's"
    assert any(calls), f"start {start_off_px} px off: the box was never used"
    if start_off_px > 1:
        assert not all(calls), f"{start_off_px} px off: every step in the box (the whole patch's path untested)"
    else:
        assert np.hypot(*(got[0] - centres).T).max() < 0.1, "near starts: the corners not found"


def test_patch_smoothing_is_kornias_gaussian_blur():
    """`_patches` smooths with taps made once (`_gaussian_taps`) through `filter2d_separable`: the same bits as
    kornia's `gaussian_blur2d` with the same size and sigma, which remakes them at every call."""
    import kornia

    rng = np.random.default_rng(12)
    gray = rng.random((120, 150)).astype(np.float32)
    for n, P, presmooth in ((1, 9, 1.4), (7, 29, 1.4), (3, 40, 1.4), (4, 15, 0.8)):
        c0 = np.c_[rng.integers(0, 150, n), rng.integers(0, 120, n)]
        ks = int(np.ceil(3 * presmooth))
        got = refine._patches(gray, c0, P, presmooth, ks)
        ys = np.clip(c0[:, 1, None] + np.arange(-P, P + 1)[None], 0, 119)
        xs = np.clip(c0[:, 0, None] + np.arange(-P, P + 1)[None], 0, 149)
        raw = torch.from_numpy(gray[ys[:, :, None], xs[:, None, :]])[:, None]
        want = kornia.filters.gaussian_blur2d(raw, (2 * ks + 1, 2 * ks + 1), (presmooth, presmooth),
                                              border_type="replicate")[:, 0]
        assert torch.equal(got, want), f"{n} patches of half-size {P}, sigma {presmooth}: not kornia's blur"


def test_pyramid_levels_are_made_when_read_and_equal_the_box_averages():
    """`build_pyramid` gives every factor at once but makes a level only when it is read (a ChArUco frame whose
    corners are found at full resolution reads no other); each level is the 2×2 box average of the one above, odd
    rows and columns dropped, down to the last whose halving stays at least `min_size` px."""
    from tiltfit.detect.imaging import build_pyramid

    rng = np.random.default_rng(13)
    for shape, factors in (((720, 1280), [1, 2, 4, 8]), ((129, 131), [1, 2]), ((127, 300), [1]), ((64, 64), [1])):
        gray = rng.random(shape).astype(np.float32)
        levels = build_pyramid(gray)
        assert list(levels) == factors and len(levels) == len(factors), f"{shape}: factors {list(levels)}"
        assert levels[1] is gray and len(levels._levels) == 1, f"{shape}: levels made before being read"
        img = gray
        for f in factors[1:]:
            h, w = img.shape[0] // 2 * 2, img.shape[1] // 2 * 2
            img = 0.25 * (img[0:h:2, 0:w:2] + img[1:h:2, 0:w:2] + img[0:h:2, 1:w:2] + img[1:h:2, 1:w:2])
            assert np.array_equal(levels[f], img) and levels[f].dtype == np.float32, f"{shape}: level {f}"
        with pytest.raises(KeyError):
            levels[2 * factors[-1]]
