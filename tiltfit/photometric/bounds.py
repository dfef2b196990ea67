"""The trust region of the photometric refinement: which lens parameters it moves and how far (`_trust_region`),
and where each ended against its bound (`_bound_record`)."""
from __future__ import annotations

import math

import torch

from renderer.cameras import (LENS_PARAMETERS, U_from_stored, d_from_stored, lens_values, stored_lens_sigma,
                              w_from_stored)

from tiltfit.calibrate.model import LensCamera
from .problem import _Problem


#: With the start's σ (`refine_photometric(start_sigma=...)`), each free lens parameter stays within this many of
#: its σ of the start (a smooth bound, start + b tanh(z / b)): the pixels cannot carry the lens far from what the
#: corners say (unbounded, stage-1 fits of real photos drifted to θF ≈ 60-80°).
TRUST_SIGMAS = 10.0


def _trust_region(cam: LensCamera, sigma: dict):
    """(free indices into LENS_PARAMETERS, (4,) bounds in stored units) from the start's σ: a parameter whose
    σ is missing, 0 or not finite is held (the start held or could not determine it)."""
    w, U, _, _ = lens_values({n: float(getattr(cam, n)) for n in LENS_PARAMETERS})
    by_name = stored_lens_sigma(w, U, sigma)
    stored = [by_name.get(n) for n in LENS_PARAMETERS]
    free = [i for i, sd in enumerate(stored) if sd is not None]
    if not free:
        free = [0]
        stored[0] = math.inf
    bound = torch.tensor([math.inf if sd is None else TRUST_SIGMAS * sd for sd in stored], dtype=torch.float64)
    return free, bound


#: Stored lens parameter -> (its name in CALIB.json, the physical value of a stored one).
_PHYSICAL = {"log_w_mm": ("w_mm", w_from_stored), "inv_U_per_m": ("U_mm", lambda v: U_from_stored(v) if v > 0 else math.inf),
             "d_scaled": ("d_mm", d_from_stored), "theta_F": ("theta_F_deg", math.degrees)}


def _bound_record(problem: "_Problem", z: torch.Tensor, at_bound: list) -> list:
    """Per free lens parameter with a finite trust bound: its start, the bound's two ends and the refined value in
    CALIB.json's units (U's ends swap: it is stored as 1/U), and whether it ended at the bound (`at_bound`)."""
    lens = problem.full_lens(z.detach())
    out = []
    for i in problem.free:
        b = float(problem.bound[i])
        if not math.isfinite(b):
            continue
        stored = LENS_PARAMETERS[i]
        name, to_physical = _PHYSICAL[stored]
        start = float(problem.lens_start[i])
        ends = sorted(to_physical(v) for v in (start - b, start + b))
        out.append({"parameter": name, "start": to_physical(start), "low": ends[0], "high": ends[1],
                    "refined": to_physical(float(lens[i])), "at_bound": stored in at_bound})
    return out
