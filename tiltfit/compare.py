"""Cross-validation of two calibrations of one camera (`tiltfit compare A.json B.json [-o DIR]`).

    compare(calib_a, calib_b) -> dict          (tiltfit.uncertainty.projection_difference, plus the inputs' names)
    summary_lines(result, name_a, name_b) -> list of str   (the one-screen summary)
    write_compare(result, out_dir) -> list of files         (compare.png: the difference map beside the predicted
                                                             one; compare.json: the numbers and both maps)

A good pair of calibrations differs by about what their uncertainties predict (mrcal's cross-validation): the
projection difference across the image after the best-fitting rotation between the two camera frames, against
sqrt(σ_A² + σ_B²) of the two projection uncertainties. Much more means an error neither σ covers.
"""
from __future__ import annotations

import json
import os

import numpy as np

from .uncertainty import projection_difference


class CompareError(ValueError):
    """Two calibrations that cannot be compared; the message names the field."""


def compare(calib_a: dict, calib_b: dict, nx: int = 32) -> dict:
    """The projection difference of two CALIB dicts (`tiltfit.uncertainty.projection_difference`).

    Raises:
        CompareError: different image sizes ("image_size_px: ...").
    """
    if [int(s) for s in calib_a["image_size_px"]] != [int(s) for s in calib_b["image_size_px"]]:
        raise CompareError(f"image_size_px: {list(calib_b['image_size_px'])} differs from the first "
                           f"calibration's {list(calib_a['image_size_px'])}")
    return projection_difference(calib_a, calib_b, nx)


def summary_lines(res: dict, name_a: str = "A", name_b: str = "B") -> list:
    """The one-screen summary of a comparison."""
    lines = [f"projection difference {name_b} vs {name_a} across the image (after the best rotation, "
             f"{res['rotation_deg']:.3g}°):",
             f"  median {res['median_px']:.3g} px, worst {res['worst_px']:.3g} px"]
    if res.get("rms_ratio") is not None:
        lines.append(f"  predicted by the two σ: median {res['predicted_median_px']:.3g} px, worst "
                     f"{res['predicted_worst_px']:.3g} px; RMS difference / RMS predicted = {res['rms_ratio']:.2f}")
    lines.append(f"  verdict: {res['verdict']}")
    return lines


def write_compare(res: dict, out_dir: str, name_a: str = "A", name_b: str = "B") -> list:
    """compare.png and compare.json in `out_dir` (written as a set); returns the paths."""
    from renderer.io import atomic_folder

    with atomic_folder(out_dir) as staging:
        _plot(res, os.path.join(staging, "compare.png"), name_a, name_b)
        with open(os.path.join(staging, "compare.json"), "w", encoding="utf-8") as f:
            json.dump(res | {"a": name_a, "b": name_b}, f, indent=1)
    return [os.path.join(out_dir, n) for n in ("compare.png", "compare.json")]


def _plot(res: dict, path: str, name_a: str, name_b: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    xs, ys = np.array(res["grid_x_px"]), np.array(res["grid_y_px"])
    maps = [("difference (px)", res["difference_px"])]
    if res.get("predicted_px") is not None:
        maps.append(("predicted sqrt(σA² + σB²) (px)", res["predicted_px"]))
    arrays = [np.array([[np.nan if x is None else x for x in row] for row in m], dtype=float) for _, m in maps]
    vmax = max(float(np.nanpercentile(a, 99)) for a in arrays) or 1.0
    fig, axes = plt.subplots(1, len(maps), figsize=(5.2 * len(maps), 4.2), squeeze=False)
    for ax, (title, _), a in zip(axes[0], maps, arrays):
        im = ax.pcolormesh(xs, ys, a, shading="nearest", vmin=0, vmax=vmax, cmap="magma")
        ax.set_ylim(ys.max(), ys.min())
        ax.set_aspect("equal")
        ax.set_title(title, fontsize=9)
        fig.colorbar(im, ax=ax, shrink=0.8)
    fig.suptitle(f"{os.path.basename(name_b)} vs {os.path.basename(name_a)}: {res['verdict']}", fontsize=8)
    try:
        fig.savefig(path, dpi=110, bbox_inches="tight")
    finally:
        plt.close(fig)
