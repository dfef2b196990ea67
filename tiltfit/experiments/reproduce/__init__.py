"""The tilt-lens paper's experiment end to end on a simulated camera (`tiltfit reproduce [--quick] [-o DIR]`).

Baba, Nakane, Hiura (IPSJ 2017), §4.2: calibrate a Canon EOS 6D with a TS-E 45 mm at f/2.8 from target
images (stage 1 untilted: w, U, d; stage 2 tilted: θL), photograph boxes on a floor at θL = 0, +5°, −5°,
re-render them as CG with the calibrated lens and compare brightness profiles along a red and a green
line (Table 1: lens tilt set → estimated; Table 2: mean brightness error per line). Here the "real"
camera is simulated, so every estimate can be checked against the truth:

(a) truth      `SimulatedCamera`: the paper's stage-1 values as the true lens (w = 55.39, U = 618.4,
               d = 18.81 mm), a tilt scale that is slightly off (the set ±5° are not the true tilts), the
               lens tilting about its centre so the focus distance moves with the tilt (hinge rule), and
               what a real camera adds to an image: vignetting, shot and read noise, 8-bit sRGB. The truth
               renders the photographs only; the calibration sees nothing but those images.
(b) targets    target photographs (the paper's Fig. 4 kind of board) at θL = 0, +5°, −5°, rendered by
               tiltfit.experiments.synth through the true lens and exposed by the simulated camera; corners and blur
               widths read back by tiltfit.detect.chessboard / tiltfit.detect.blur as from any photograph.
(c) calibrate  stage 1 (unified, eq. 3) + stage 2 (tilt, eq. 4, the paper) + joint (tiltfit.calibrate.fit), from the
               detections only, started from the set values; Table 1 and the stage-1 table.
(d) boxes      the boxes scene photographed with the true lens at the three lens states, re-rendered as
               CG with (i) the set values and (ii) the calibrated values; profiles along the red and the
               green line; Table 2 (mean brightness error per line, lens state and parameter set) and the
               noise floor (two independent photographs of the same scene compared).
(e) plots      photographs and CG side by side with the lines (Figs. 11–13), profiles real vs CG (Figs. 14,
               15), speed–accuracy (CG samples per pixel against error and render time).
(f) outputs    Markdown and CSV tables, PNG plots and images, the scene files of every render, a JSON with
               the data of every figure and a run record, all in DIR; the two tables on stdout, progress
               on stderr.

`RunConfig.calibrate` False skips stages (b) and (c) (a look at the set values alone): Table 1 then marks
the estimates "not run" and Table 2 has no calibrated rows. A fit that fails is reported, not papered over.
Nothing is filled in by hand: every number in the outputs is computed by the run.

Modules (one stage each):
    config       `RunConfig`, the lens states, `SimulatedCamera` (a), `SetValues`, and the renders, noise,
                 images and seeds every stage shares
    targets      (b) the target photographs (`calibration_target`, `TARGET_VIEWS`, `target_pose`, `stage_targets`)
    calibration  (c) the fits and Table 1 / the stage-1 table
    boxes        (d) the boxes photographs and CG, Table 2 and the noise floor
    figures      (e) the speed–accuracy sweep and the figures
    pipeline     (f) `run` and `main` (`tiltfit reproduce`, `python -m tiltfit.experiments.reproduce`)
The package exports what other code uses: `run`, `main`, `RunConfig`, `SimulatedCamera`, `SetValues`, the
lens states and the target, its views and poses.
"""
from .boxes import NOISE_FLOOR, TRUE_LENS
from .config import LENS_STATES, LensState, RunConfig, SetValues, SimulatedCamera
from .pipeline import ReproduceResult, main, run
from .targets import MIN_CORNER_FRACTION, TARGET_VIEWS, calibration_target, target_pose

__all__ = ["LENS_STATES", "MIN_CORNER_FRACTION", "NOISE_FLOOR", "TARGET_VIEWS", "TRUE_LENS", "LensState",
           "ReproduceResult", "RunConfig", "SetValues", "SimulatedCamera", "calibration_target", "main", "run",
           "target_pose"]
