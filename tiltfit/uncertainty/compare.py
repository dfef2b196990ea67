"""Cross-validation of two calibrations of one camera (`tiltfit compare A.json B.json [-o DIR]`).

    compare(calib_a, calib_b, rotation=True) -> dict  (tiltfit.uncertainty.covariance.projection_difference, plus the
                                                     intrinsics' differences B − A and the views both share)
    shared_views(calib_a, calib_b) -> list of (i, j)  (views of A that are views of B)
    summary_lines(result, name_a, name_b) -> list of str   (the one-screen summary, A before B)
    write_compare(result, out_dir) -> list of files         (compare.png: the difference map beside the predicted
                                                             one; compare.json: the numbers and both maps)

A good pair of calibrations differs by about what their uncertainties predict (mrcal's cross-validation): the
projection difference across the image after the best-fitting rotation between the two camera frames, against
sqrt(σ_A² + σ_B²) of the two projection uncertainties. Much more means an error neither σ covers.

Order: A is the first calibration, B the second, everywhere (text, plots, compare.json); every signed difference
is B − A, and the rotation turns A's camera frame into B's.

The rotation absorbs a common shift of the principal point: shifting the principal point by Δ px while every
pose turns by about Δ/f rad projects the board the same way, so two calibrations that differ by such a shift
show no difference after the rotation (as in mrcal-show-projection-diff). The shift itself is reported beside it
(`principal_point_difference_px`), and `rotation=False` compares the projections of the same camera-frame
directions, the shift counting in full.

Independence: sqrt(σ_A² + σ_B²) is the yardstick only for calibrations made from different views. Views both
use (the same photo, or the board in the same place: detected corners within `SAME_VIEW_PX`) share their errors,
so the two results differ less than predicted; `compare` names how many views are shared (`warning`) and gives
no verdict when all of them are.
"""
from __future__ import annotations

import json
import math
import os
import re

import numpy as np

from tiltfit.uncertainty.covariance import covariance_from_calib, intrinsics_vector, projection_difference

#: Two views whose detected corners agree to this RMS (px) are one view (the same photo, or the board in the same
#: place: their errors are shared).
SAME_VIEW_PX = 0.5

# `tiltfit.calibrate.model.Observations` names views without file names "view<N>": such names say nothing about the photo.
_PLACEHOLDER = re.compile(r"view\d+")


class CompareError(ValueError):
    """Two calibrations that cannot be compared; the message names the field."""


def compare(calib_a: dict, calib_b: dict, nx: int = 32, rotation: bool = True) -> dict:
    """The projection difference of two CALIB dicts (`tiltfit.uncertainty.covariance.projection_difference`), plus
    `focal_difference_px` and `principal_point_difference_px` (B − A), `shared_views` {n, n_a, n_b, images (A's
    names)} and, when views are shared, `warning` (one line); with every view shared, no verdict
    (`consistent` None).

    Raises:
        CompareError: different image sizes ("image_size_px: ..."), or an `intrinsics_covariance` that is not a
            covariance (`tiltfit.uncertainty.covariance.covariance_problem`).
    """
    if [int(s) for s in calib_a["image_size_px"]] != [int(s) for s in calib_b["image_size_px"]]:
        raise CompareError(f"image_size_px: {list(calib_b['image_size_px'])} differs from the first "
                           f"calibration's {list(calib_a['image_size_px'])}")
    for which, calib in (("the first calibration", calib_a), ("the second calibration", calib_b)):
        try:
            covariance_from_calib(calib)
        except ValueError as e:
            raise CompareError(f"{which}: {e}") from None
    res = projection_difference(calib_a, calib_b, nx, rotation=rotation)
    ta, tb = intrinsics_vector(calib_a), intrinsics_vector(calib_b)
    res["focal_difference_px"] = float(tb[0] - ta[0])
    res["principal_point_difference_px"] = [float(tb[1] - ta[1]), float(tb[2] - ta[2])]
    pairs = shared_views(calib_a, calib_b)
    views_a, views_b = calib_a.get("views") or [], calib_b.get("views") or []
    n, n_a, n_b = len(pairs), len(views_a), len(views_b)
    res["shared_views"] = {"n": n, "n_a": n_a, "n_b": n_b,
                           "images": [str(views_a[i].get("image", f"view{i}")) for i, _ in pairs]}
    if n:
        whole = n == n_a == n_b
        res["warning"] = (f"{'all ' if whole else ''}{n} {'view is' if n == 1 else 'views are'} in both calibrations (of {n_a} and {n_b}): "
                          f"the predicted difference assumes independent calibrations and is then not the right "
                          f"yardstick (shared views make them agree more than it says)")
        if whole:
            res |= {"consistent": None,
                    "verdict": f"no verdict: both calibrations use the same {n} views, so the difference shows "
                               f"only how their settings differ, not whether either is within its σ"}
    return res


def shared_views(calib_a: dict, calib_b: dict) -> list:
    """Pairs (i, j): view i of A is view j of B.

    Where both files hold the detected corners (views[].corners_px), two views are one when those agree to
    `SAME_VIEW_PX` RMS over the corners both found (the same photo, or the board in the same place); otherwise
    when their image names agree (the file name without its folder; not the placeholders "view<N>" of
    calibrations made without file names).
    """
    views_a, views_b = calib_a.get("views") or [], calib_b.get("views") or []
    corners_b = [_corners(v) for v in views_b]
    names_b = [_name(v) for v in views_b]
    pairs, used = [], set()
    for i, va in enumerate(views_a):
        ca, na = _corners(va), _name(va)
        for j, vb in enumerate(views_b):
            if j in used:
                continue
            cb = corners_b[j]
            if ca is not None and cb is not None:
                same = ca.shape == cb.shape and _corner_rms(ca, cb) <= SAME_VIEW_PX
            else:
                same = na is not None and na == names_b[j]
            if same:
                pairs.append((i, j))
                used.add(j)
                break
    return pairs


def _name(view: dict):
    name = str(view.get("image") or "").replace("\\", "/").rsplit("/", 1)[-1]
    return None if not name or _PLACEHOLDER.fullmatch(name) else name


def _corners(view: dict):
    """(n, 2) detected corners, NaN where missing; None without them."""
    c = view.get("corners_px")
    if not isinstance(c, list) or not c:
        return None
    return np.array([p if isinstance(p, list) and len(p) == 2 and None not in p else [math.nan, math.nan]
                     for p in c], dtype=float)


def _corner_rms(ca, cb) -> float:
    both = np.isfinite(ca).all(-1) & np.isfinite(cb).all(-1)
    if both.sum() < 4:
        return math.inf
    return float(np.sqrt(np.mean(np.sum((ca[both] - cb[both]) ** 2, -1))))


def summary_lines(res: dict, name_a: str = "A", name_b: str = "B") -> list:
    """The one-screen summary of a comparison: A first, B second, signed differences B − A."""
    if res.get("rotation_fitted", True):
        head = (f"projection difference {name_a} vs {name_b} across the image, after the best-fitting rotation "
                f"from {name_a}'s camera frame to {name_b}'s ({res['rotation_deg']:.3g}°):")
        shift = "the rotation absorbs a common shift of the principal point (the poses turn with it)"
    else:
        head = f"projection difference {name_a} vs {name_b} across the image, no rotation fitted:"
        shift = "no rotation fitted: a shift of the principal point counts in full"
    lines = [head, f"  median {res['median_px']:.3g} px, worst {res['worst_px']:.3g} px"]
    if res.get("predicted_median_px") is not None:
        lines.append(f"  predicted by the two σ: median {res['predicted_median_px']:.3g} px, worst "
                     f"{res['predicted_worst_px']:.3g} px; RMS difference / RMS predicted = {res['rms_ratio']:.2f}")
    if res.get("principal_point_difference_px") is not None:
        dx, dy = res["principal_point_difference_px"]
        shift += (f"; {name_b} − {name_a}: principal point ({dx:+.3g}, {dy:+.3g}) px, focal length "
                  f"{res['focal_difference_px']:+.3g} px")
    lines.append(f"  {shift}")
    lines.append(f"  verdict: {res['verdict']}")
    return lines


def write_compare(res: dict, out_dir: str, name_a: str = "A", name_b: str = "B") -> list:
    """compare.png and compare.json in `out_dir` (written as a set); returns the paths."""
    from camio.files import atomic_folder

    with atomic_folder(out_dir) as staging:
        _plot(res, os.path.join(staging, "compare.png"), name_a, name_b)
        with open(os.path.join(staging, "compare.json"), "w", encoding="utf-8") as f:
            json.dump(res | {"a": name_a, "b": name_b}, f, indent=1)
    return [os.path.join(out_dir, n) for n in ("compare.png", "compare.json")]


def plot_titles(res: dict, name_a: str, name_b: str) -> tuple:
    """(the figure's title, the difference map's title): A before B."""
    a, b = os.path.basename(name_a), os.path.basename(name_b)
    how = (f"after the best-fitting rotation {a} → {b} ({res['rotation_deg']:.3g}°; it absorbs a common "
           f"principal-point shift)" if res.get("rotation_fitted", True) else "no rotation fitted")
    title = f"{a} vs {b}: {res['verdict']}\n{how}"
    if res.get("warning"):
        title += f"\n{res['warning']}"
    return title, f"difference {a} vs {b} (px)"


def _plot(res: dict, path: str, name_a: str, name_b: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    title, diff_title = plot_titles(res, name_a, name_b)
    xs, ys = np.array(res["grid_x_px"]), np.array(res["grid_y_px"])
    maps = [(diff_title, res["difference_px"])]
    if res.get("predicted_px") is not None:
        maps.append(("predicted sqrt(σA² + σB²) (px)", res["predicted_px"]))
    arrays = [np.array([[np.nan if x is None else x for x in row] for row in m], dtype=float) for _, m in maps]
    vmax = max(float(np.nanpercentile(a, 99)) for a in arrays) or 1.0
    fig, axes = plt.subplots(1, len(maps), figsize=(5.2 * len(maps), 4.2), squeeze=False)
    for ax, (t, _), a in zip(axes[0], maps, arrays):
        im = ax.pcolormesh(xs, ys, a, shading="nearest", vmin=0, vmax=vmax, cmap="magma")
        ax.set_ylim(ys.max(), ys.min())
        ax.set_aspect("equal")
        ax.set_title(t, fontsize=8, wrap=True)
        fig.colorbar(im, ax=ax, shrink=0.8)
    fig.suptitle(title, fontsize=8)
    try:
        fig.savefig(path, dpi=110, bbox_inches="tight")
    finally:
        plt.close(fig)
