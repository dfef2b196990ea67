"""The usable-pixel mask's guard on the real sets: per view, usable pixels with the guard's chief-ray length taken
from the rays that meet the board's plane near the board (tiltfit.photometric.render.usable_pixels now) and
from every candidate of the board's box (before: a grazing ray of a GoPro view met the plane 255 m away and
left 0 usable pixels). Candidates as `pixels._choose_pixels` draws them; corner fits unified, free principal
point, opencv5: industrial_ds1's 6 even views of the first 12, gopro_wide's and its three thirds.

    python benchmarks/history/diag_usable_guard.py

Prints one line per view set: (longest chief ray of the candidates mm, usable now, usable before, same mask).
"""
import os
import sys
import time

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
sys.path.insert(0, ROOT)

import numpy as np  # noqa: E402
import torch  # noqa: E402


def main() -> int:
    from tests.real_detections import observations
    from renderer import read_image
    from tiltfit.calibrate.flow import calibrate
    from tiltfit.calibrate.fit import FitOptions
    from tiltfit.photometric import PhotometricOptions, pixels, render
    from tiltfit.target.layout import load_target

    torch.set_num_threads(1)
    rows, plain = [], render.usable_pixels

    def both(target, cam, uv, t_max=None):
        with torch.no_grad():
            rays = cam.generate_rays(uv)
            t = -rays.origin[..., 2] / rays.direction[..., 2]
        longest = float(t.abs().max())
        now, before = plain(target, cam, uv), plain(target, cam, uv, t_max=longest)
        rows.append((round(longest, 1), int(now.sum()), int(before.sum()), bool((now == before).all())))
        return now

    pixels.usable_pixels = both
    for name, pitch, n in (("industrial_ds1", 0.0048, 20), ("gopro_wide", 0.005, 35)):
        folder = os.path.join(ROOT, "data", "real", name)
        target = load_target(os.path.join(folder, "target.json"))
        obs, _ = observations(folder, pitch)
        groups = [list(range(0, 12, 2))] + ([list(range(g, obs.n_views, 3)) for g in range(3)] if name == "gopro_wide" else [])
        for views in groups:
            sub = obs.subset(views)
            fit = calibrate(sub, "unified", options=FitOptions(free_principal_point=True, distortion="opencv5",
                                                               model_selection=False))
            cam = fit.camera.copy().double()
            imgs = []
            for f in sub.names:
                im = np.asarray(read_image(os.path.join(folder, f)), dtype=np.float64)
                imgs.append(im.mean(-1) if im.ndim == 3 else im)
            rows.clear()
            try:
                pixels._choose_pixels(imgs, [cam.view_camera(v) for v in range(cam.n_views)], target,
                                      PhotometricOptions(max_pixels=1000), True, None, time.perf_counter())
            except pixels._ViewsLeftOut as e:
                print(f"  left out: {e.views}")
            print(name, f"views {views[0]}, {views[1]}, …:", rows, flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
