"""The automatic choices on small boards (issue 33 §5): a board model the views cannot carry is not tried, the
distortion terms follow the one-standard-error rule, and σ holds the spread over the models the held-out views
cannot tell apart."""
from __future__ import annotations

import csv
import math
import os

import numpy as np
import pytest
import torch

from tiltfit.calibrate.model import Observations

HERE = os.path.dirname(os.path.abspath(__file__))
CHARUCO = os.path.join(HERE, "..", "data", "charuco_webcam", "published_corners_4views.csv")


def views_obs(per_view_px, corners=24):
    """Observations of len(per_view_px) views of a 6×4 board, every corner seen (only the counts matter)."""
    V = len(per_view_px)
    pts = torch.tensor([[10.0 * (i % 6), 10.0 * (i // 6), 0.0] for i in range(corners)])
    return Observations(pts, torch.zeros(V, corners, 2), torch.full((V, corners), math.nan), (64, 48), 0.01)


def test_one_standard_error_rule_keeps_fewer_terms_within_the_scatter_over_the_views():
    """k1 and opencv5 held out on six views: opencv5 better by 3 % on average but carried by one view keeps k1 (the
    1 % rule took opencv5); the same 3 % on every view takes opencv5."""
    from tiltfit.select.held_out import _fewest_terms_within_one_se

    models = ("k1", "opencv5")
    k1 = {"per_view_px": [0.30] * 6, "rms_px": 0.30}
    lone = math.sqrt(0.30 ** 2 - 6 * (0.30 ** 2 - 0.291 ** 2))
    one_view = {"per_view_px": [lone] + [0.30] * 5}
    one_view["rms_px"] = math.sqrt(np.mean(np.square(one_view["per_view_px"])))
    every = {"per_view_px": [0.291, 0.2912, 0.2908, 0.291, 0.2911, 0.2909]}
    every["rms_px"] = math.sqrt(np.mean(np.square(every["per_view_px"])))
    obs = views_obs(k1["per_view_px"])
    for rich, expected in ((one_view, "k1"), (every, "opencv5")):
        entries = [{"model": m} for m in models]
        held = {"k1": k1, "opencv5": rich}
        scores = {m: held[m]["rms_px"] for m in models}
        assert scores["opencv5"] < 0.99 * scores["k1"], "the richer model beats the 1 % tolerance in both cases"
        got = _fewest_terms_within_one_se(models, scores, held, obs, entries)
        assert got == expected, f"chose {got} with per-view errors {rich['per_view_px']}"


def test_choice_variance_weighs_models_as_the_choice_does():
    """Two models 30 px apart in cx. Indistinguishable over the views (z ≈ 0) with the rule asking 1 standard error
    of the richer one: the simpler one is chosen and σ holds the richer one at the prior odds exp(-1/2); the richer
    one many standard errors better but not chosen: σ holds nearly all of the difference; chosen: nothing."""
    from tiltfit.select.held_out import choice_variance

    def held(per_view):
        return {"per_view_px": per_view, "rms_px": math.sqrt(np.mean(np.square(per_view)))}

    simple = ({"w_mm": 10.0, "principal_point_px": [617.0, 497.0]}, held([0.30] * 6))
    rich = {"w_mm": 10.1, "principal_point_px": [647.0, 467.0]}
    tie = (rich, held([0.2999, 0.3001, 0.2999, 0.3001, 0.2999, 0.3001]))
    better = (rich, held([0.29, 0.291, 0.289, 0.29, 0.292, 0.288]))
    obs = views_obs([0.3] * 6)
    v = choice_variance({"k1": simple, "opencv5": tie}, "k1", obs, 1.0)
    w = math.exp(-0.5) / (1 + math.exp(-0.5))
    s = np.sqrt(v["principal_point_px"])
    assert np.allclose(s, 30 * math.sqrt(w), rtol=0.01), f"σ of the principal point {s}, expected {30 * math.sqrt(w)}"
    assert math.isclose(math.sqrt(v["w_mm"]), 0.1 * math.sqrt(w), rel_tol=0.01), f"σ of w {math.sqrt(v['w_mm'])}"
    wrong = choice_variance({"k1": simple, "opencv5": better}, "k1", obs, 1.0)
    assert 29 < math.sqrt(wrong["principal_point_px"][0]) <= 30, f"the better model left out: {wrong}"
    right = choice_variance({"k1": simple, "opencv5": better}, "opencv5", obs, 1.0)
    assert max(right["principal_point_px"]) < 1e-6, f"a model many standard errors worse adds {right}"
    stricter = choice_variance({"flat": simple, "free": tie}, "flat", obs, 2.0)
    assert stricter["principal_point_px"][0] < 0.5 * v["principal_point_px"][0], \
        f"a rule asking 2 standard errors weighs the richer model less: {stricter} vs {v}"
    assert choice_variance({"k1": simple}, "k1", obs, 1.0) is None, "one model: no choice, no variance"


def charuco_four_views():
    """Observations of the 4-view ChArUco case (published corners, 3×4 inner corners of 54 mm squares)."""
    rows = list(csv.DictReader(open(CHARUCO)))
    frames = sorted({int(r["frame"]) for r in rows})
    pts = np.array([[(k % 3 + 1) * 54.0, (k // 3 + 1) * 54.0, 0.0] for k in range(12)])
    uv = np.full((len(frames), 12, 2), np.nan)
    for r in rows:
        uv[frames.index(int(r["frame"])), int(r["corner_id"])] = float(r["x_px"]), float(r["y_px"])
    return Observations(pts, uv, np.full(uv.shape[:2], np.nan), (1280, 720), 0.003, [f"frame_{f}" for f in frames])


@pytest.mark.slow
def test_four_charuco_views_do_not_take_a_free_board():
    """4 views of 12 ChArUco corners (48 corners for the free board's 29 parameters): free is not tried, and the focal
    length is that of the whole stream (OpenCV on all 46 frames: 883 px; the issue's free board gave 396 ± 43 on
    such a set)."""
    from tiltfit.calibrate.flow import calibrate
    from tiltfit.calibrate.fit import FitOptions

    obs = charuco_four_views()
    res = calibrate(obs, "unified", options=FitOptions(distortion="auto", board="auto"))
    free = next(e for e in res.board_selection if e["model"] == "free")
    assert "too few corners" in free.get("refused", ""), f"free was tried on 48 corners: {free}"
    assert res.board is None or res.board.model != "free", f"board {res.board.model} chosen"
    f, s = res.values["w_mm"] / obs.pixel_pitch_mm, res.sigma["w_mm"] / obs.pixel_pitch_mm
    assert 800 < f < 960, f"f = {f:.1f} ± {s:.2g} px (OpenCV on all 46 frames: 883)"
    assert 3 < s < 60, f"σ of f {s:.3g} px from 4 views"
    assert abs(f - 883) < 3 * s + 10, f"f = {f:.1f} ± {s:.2g} px against 883"


@pytest.mark.parametrize("model", ["free"])
def test_a_board_asked_for_by_name_is_still_fitted(model):
    """The rule only bounds the automatic choice: `--board free` on the same 48 corners is fitted or refused by the
    fit itself, never by the corner count."""
    from tiltfit.select.board import select_board
    from tiltfit.calibrate.flow import fit_geometry
    from tiltfit.calibrate.fit import FitOptions

    obs = charuco_four_views()
    opts = FitOptions(distortion="k1", free_principal_point=False, model_selection=False)
    from tiltfit.calibrate.start import initialize

    flat = fit_geometry(initialize(obs, "unified", None, opts, blur=False), obs, opts)
    try:
        _, entries = select_board(flat.camera, obs, opts, models=(model,))
    except Exception as e:  # the fit itself may fail on so few corners; that is not the rule
        assert "too few corners" not in str(e), f"asked for by name and refused by the corner count: {e}"
        return
    assert "too few corners" not in entries[0].get("refused", ""), f"asked for by name: {entries[0]}"


@pytest.mark.slow
def test_industrial_quarters_choose_alike_and_sigma_covers_their_spread():
    """industrial_ds1 dealt into four quarters of 5 views (cached detections): every quarter takes the same board and
    distortion terms (E's σ-ratio rule sent one to flat/rational, 15-45 px from the others), and the principal
    points' spread over the pairs of quarters is what σ says: pooled spread/σ between 0.3 and 2 (it was 5.4)."""
    import itertools
    import sys

    root = os.path.join(HERE, "..", "..")
    sys.path.insert(0, os.path.join(root, "tests"))
    from real_detections import observations

    from tiltfit.calibrate.flow import calibrate
    from tiltfit.calibrate.fit import FitOptions

    obs, _ = observations(os.path.join(root, "data", "real", "industrial_ds1"), 0.0048)
    fits = [calibrate(obs.subset([v for v in range(obs.n_views) if v % 4 == k]), "unified",
                      options=FitOptions(distortion="auto", board="auto")) for k in range(4)]
    choices = {((r.board.model if r.board is not None else "flat"), r.distortion_model) for r in fits}
    assert len(choices) == 1, f"the quarters chose {choices}"
    pp = np.array([r.values["principal_point_px"] for r in fits])
    s = np.array([r.sigma["principal_point_px"] for r in fits])
    z2 = [(pp[a] - pp[b]) ** 2 / (s[a] ** 2 + s[b] ** 2) for a, b in itertools.combinations(range(4), 2)]
    pooled = float(np.sqrt(np.mean(z2)))
    assert 0.3 < pooled < 2.0, f"spread/σ of the principal point over the quarters {pooled:.2f}: {pp} ± {s}"
