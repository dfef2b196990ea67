"""Build docs/file_formats.md and docs/schemas/*.json from the code's own declarations.

    python -m tiltfit.files.formats [--check]

The scene part comes from `renderer.scene.formats` (the validator's `Param` tables); the target, DET and CALIB parts
from the constants the readers use (`tiltfit.target.layout`, `tiltfit.files.det`, `tiltfit.files.calib`). `--check` exits
1 when the committed files differ from a fresh build (the test suite runs the same comparison).
"""
from __future__ import annotations

import argparse
import json
import os
import sys

from renderer.core.params import DISTORTION_CENTRES
from renderer.scene.formats import SCHEMA_DIALECT, scene_reference, scene_schema
from camio.checks import MAX_JSON_DEPTH

from tiltfit.files import calib as calibfile
from tiltfit.files import det as detfile
from tiltfit.target import layout as target

DOCS = os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))), "docs")

TARGET_FIELDS = [
    ("type", "string", "required", '"checkerboard" (this table) or "charuco" (the next)'),
    ("units", "string", '"mm"', '"mm" (the only unit)'),
    ("x_edges", "list of numbers", "required", f"ascending column boundaries, mm; 3 to {target.MAX_EDGES} values "
                                               f"within ±{target.MAX_MM:g}"),
    ("y_edges", "list of numbers", "required", "ascending row boundaries, mm; as `x_edges`"),
    ("dark_cell", "[int, int]", "[0, 0]", "a (column, row) cell that is dark; only the parity of the sum matters"),
    ("margin", "number", "25", f"white border around the checkered area, mm, 0 to {target.MAX_MM:g}"),
    ("inverted", "boolean", "false", "true for a board printed white on black (light cells, markers and margin "
     "dark, dark ones light): detection inverts the photo first; without it such a board is refused with a hint"),
    ("name, description", "string", "—", "free text"),
]

CHARUCO_FIELDS = [
    ("type", "string", "required", '"charuco": a ChArUco board as OpenCV\'s `cv2.aruco.CharucoBoard` draws it'),
    ("units", "string", '"mm"', '"mm" (the only unit)'),
    ("dictionary", "string", "required", "OpenCV's ArUco dictionary, e.g. `DICT_5X5_100` (`cv2.aruco.DICT_*`); it "
                                         "must hold a marker for every white cell"),
    ("squares", "[int, int]", "required", f"[columns, rows] of squares, each 2 to {target.MAX_EDGES - 1} (OpenCV's "
                                          "`size`); the checkered area spans [0, columns · square_mm] × [0, rows · "
                                          "square_mm]"),
    ("square_mm", "number", "required", "side of a square, mm"),
    ("marker_mm", "number", "required", "side of a marker incl. its one-bit black border, mm, below `square_mm`"),
    ("dark_cell", "[int, int]", "[0, 0]", "even parity: the top-left square dark (OpenCV ≥ 4.6); odd: OpenCV's "
                                          "legacy pattern, only for an even number of rows"),
    ("margin", "number", "25", f"white border around the checkered area, mm, 0 to {target.MAX_MM:g}"),
    ("inverted", "boolean", "false", "true for a board printed white on black (light cells, markers and margin "
     "dark, dark ones light): detection inverts the photo first; without it such a board is refused with a hint"),
    ("name, description", "string", "—", "free text"),
]

DET_FIELDS = [
    ("image_size_px", "[int, int]", "required", f"[width, height], pixels, each 1 to {detfile.MAX_IMAGE_SIDE}"),
    ("corners_px", "list of [x, y] or null", "required", "one per feature point (target order); "
                                                         + detfile.UNITS["corners_px"] + "; inside the image"),
    ("blur_px", "list of numbers or null", "required", "one per feature point; " + detfile.UNITS["blur_px"]
     + "; 0 to the image diagonal (negative widths are refused)"),
    ("grid_found", "bool", "—", "the board was found and indexed without ambiguity"),
    ("format_version", "int", str(detfile.DET_FORMAT_VERSION), "refused when newer than this tiltfit's"),
    ("image", "string", "—", "the image the corners were found in"),
    ("target", "object", "—", "`{file, n_points, x_edges_count, y_edges_count}` of the target used"),
    ("units", "object", "—", "what each array holds and in which unit (the texts above)"),
    ("created", "string", "—", "UTC date and time, ISO 8601"),
    ("software", "string", "—", '"tiltfit <version>"'),
]


def _table(rows) -> str:
    out = ["| key | kind | default | meaning |", "|---|---|---|---|"]
    out += [f"| `{k}` | {kind} | {d} | {m} |" for k, kind, d, m in rows]
    return "\n".join(out)


def calibration_reference() -> str:
    """Markdown reference of the target, DET and CALIB files and of what reading them checks."""
    return "\n".join(_target_lines() + _det_lines() + _calib_lines() + _photometric_lines()
                     + _uncertainty_lines() + _json_lines())


def _target_lines() -> list:
    """The target-file section: checkerboard and ChArUco keys."""
    return [
        "## Target files (`--target T.json`)", "", _table(TARGET_FIELDS), "",
        "Unknown keys are refused. Feature points are the interior intersections, row by row.", "",
        "ChArUco boards (`\"type\": \"charuco\"`):", "", _table(CHARUCO_FIELDS), "",
        "Feature point k is OpenCV's ChArUco corner id k (row by row, as for checkerboards); marker m sits in the "
        "m-th white cell, row by row. A DET file of a ChArUco view lists every corner of the board, `null` where "
        "it was not seen, so partial views need nothing new. Detection, blur and calibration: "
        "[charuco.md](charuco.md).", "",
    ]


def _det_lines() -> list:
    """The DET-file section: its keys and the checks of a view."""
    return [
        "## Detection files (`tiltfit detect -o DET.json`)", "", _table(DET_FIELDS), "",
        "Checks when `tiltfit calibrate` reads DET files (or detects images): every number finite; each view has at "
        "least 6 corners (`tiltfit.calibrate.model.MIN_CORNERS`, the fit's `min_corners` too; `tiltfit target design` refuses "
        "boards with fewer) that do not lie on one line (in the image or on the target); no view repeats another's "
        "detections (a copy would shrink σ as if it were new evidence); no view is a mirror image of the target "
        "(a flipped photo, or the board seen from behind).", "",
    ]


def _calib_lines() -> list:
    """The CALIB-file section: its keys, ranges, models, board and the checks when reading it."""
    return [
        "## Calibration files (`tiltfit calibrate -o CALIB.json`, `--init`)", "",
        "Keys: " + ", ".join(f"`{k}`" for k in calibfile.REQUIRED_KEYS) + "; each view: "
        + ", ".join(f"`{k}`" for k in calibfile.VIEW_KEYS) + "; `sigma`: "
        + ", ".join(f"`{k}`" for k in calibfile.SIGMA_KEYS) + " (one standard deviation). Lengths in mm, angles in "
        "degrees, pixels as in the DET file. Non-finite values are written as null.", "",
        "Reprojection RMS (`rms_reprojection_px` of each view and of all views, `held_out.rms_px`, and what stderr, "
        "`tiltfit report` and `tiltfit export` show) is per corner, OpenCV's definition (the value "
        "`cv2.calibrateCamera` returns): sqrt(mean over corners of dx² + dy²), √2 times an RMS per coordinate.", "",
        "Values are never written outside their physical range: `w_mm` > 0; `U_mm` > 0 or null; `d_mm` ≥ 0 or null; "
        "a key the data cannot determine, or whose fit left its range (U ≤ 0: focus beyond infinity), is null and "
        "listed in `undetermined`. `tiltfit export` accepts every file `tiltfit calibrate` writes. Also written: "
        "`warnings` (e.g. that the thin-lens blur model does not describe the lens, that the blur widths do not "
        "determine the focus, or that the blur residuals trend with depth), `principal_point_fitted`, "
        "`model_selection.principal_point` (`justified`, `fitted`), `model_selection.blur` (`used`: whether the "
        "blur widths gave U and d; `why_not`: why the thin-lens blur model was refused or why the widths do not "
        "determine the focus, null where neither; `noise_px`: the widths' noise from neighbouring corners; "
        "`trend_with_depth`: `significant`, `p_value`, `amplitude_px`, `depth_mm` of the blur residuals' trend "
        "with depth, where tested) and `distortion_selection` (per model: fit `rms_px`, `held_out_rms_px` or why "
        "it was `refused`, `chosen`, and `board`: the board model fitted with it and refitted in each fold, where "
        "the board's shape is fitted; the distortion is chosen again then, among the flat board's choice, the "
        "models with fewer terms, and the richer ones the flat board's fit refused only for an uncertain "
        "projection). The models (`distortion_model`; the coefficients are always the eight of OpenCV's rational "
        "model, those a model does not fit 0): `none`, `k1`, `k1k2`, `opencv5` (k1 k2 p1 p2 k3), `rational5` (k1 "
        "k2 p1 p2 k4: OpenCV's rational model with k3, k5, k6 held at 0, a first-order denominator; `tiltfit export "
        "--to opencv` writes its `flags`, CALIB_RATIONAL_MODEL | CALIB_FIX_K3 | CALIB_FIX_K5 | CALIB_FIX_K6), "
        "`rational` (all eight).", "",
        "`distortion_centre` (default `\"sensor\"`): `\"sensor\"`, the distortion about the principal point, or "
        "`\"lens_axis\"`, about the tilted lens's own axis (applied in the lens's frame, OpenCV's tilted model: "
        "`tiltfit export --to opencv` then writes τx, τy, and refuses the file, naming `theta_L_deg`, where θL is "
        "undetermined (null, with θF ≠ 0): τ = 0 would be another camera; mrcal's file says the tilt is unknown and "
        "its projection approximate); the joint fit chooses it by a likelihood-ratio test "
        "(`model_selection.distortion_centre`: `lr_statistic`, `p_value`, `delta_bic`, `justified`, `chosen`). "
        "Checked when reading: one of " + ", ".join(f"`{c}`" for c in DISTORTION_CENTRES) + "; `theta_L_deg`, "
        "where given, |θL| < 90 (a file with θL but no θF, as read from an OpenCV τ file, starts θF from θL).", "",
        "The target as fitted (`--board auto|flat|warp|free`, `tiltfit.target.shape`): `board` with `model` (`flat`: the "
        "target file's points; `warp`: `parameters` `sag_x_mm`, `sag_y_mm` (the board's bow out of its plane at its "
        "centre relative to its edges, along X and along Y, mm, +Z of the target frame) and `scale_y_minus_1` (the "
        "print scale along Y relative to X; the scale along X is the target file's, since no corner fit sees the "
        "board's overall size), with their `sigma`; `free`: every point's `points_mm` [X, Y, Z] and "
        "`sigma_points_mm`, the first point, the last point of the first row and the Z of the last point held as "
        "the gauge, as OpenCV's calibrateCameraRO), `max_offset_in_plane_mm`, `max_offset_out_of_plane_mm`; "
        "`board_selection` (per model: fit `rms_px`, K-fold `held_out_rms_px`, `chosen`: a richer model is chosen "
        "where it predicts held-out views better than every simpler one by 1 % and the one it displaces by 2 "
        "standard errors over the views, `gain_z`; `not_chosen` says why not; `refused`: not tried where the views "
        "give fewer than 2 corners per parameter; `sigma_ratio`: the lens's σ over the flat board's, recorded), "
        "and per view "
        "`residuals_flat_board_px` (the same lens with the flat points, each view's pose refitted). Checked where present when reading; "
        "`--init` and `tiltfit export` use the camera and ignore the board.", "",
        "Checks when reading (`--init`): `pixel_pitch_mm`, `w_mm`, `U_mm`, `d_mm` positive and at most "
        f"{calibfile.MAX_LENGTH_MM:g} mm; `image_size_px` two integers 1 to {detfile.MAX_IMAGE_SIDE}; `principal_point_px` within one "
        "image size of the image; `|theta_F_deg| < 90`; each view's `R` a rotation (orthonormal, determinant +1, "
        f"finite) and `T_mm` within ±{calibfile.MAX_LENGTH_MM:g} mm.", "",
    ]


def _photometric_lines() -> list:
    """The CALIB-file paragraph of `--refine photometric`: the `photometric` block."""
    from tiltfit.photometric import CLOSED_FORM_MIN_BLUR_PX, MIN_USABLE_PIXELS

    return [
        "After `--refine photometric`: `refinement: \"photometric\"` and a `photometric` block with the corner "
        "fit it started from (`corner_fit`, `corner_fit_sigma`), `rms_linear` (photometric RMS, linear units), "
        "`iterations`, `runtime_s`, `vignetting`, per-view `levels` (`white`, `black`; null for a view left out), "
        "`left_out`: the views left out of the fit (`view` index, `image`, `reason`: fewer than "
        f"{MIN_USABLE_PIXELS} usable pixels, those whose blur disc lies on the board inside its margin, saturated "
        "ones dropped, or no board on the image at the start; also one line on stderr each), whose poses stay the "
        "corner fit's and which have no `rms_photometric` (the refinement stops only where no view is left), "
        "the blur `kernel` "
        "(`disc` or `disc_gaussian`), `psf_sigma_px` and its σ `psf_sigma_px_sigma` (0 for the disc), how each pixel "
        "integrated the lens's `aperture`: `closed_form` (exact over the aperture; 8 x 8 points a pixel where its blur "
        "disc is under 3 px, 4 x 4 elsewhere) for every pixel with the disc kernel"
        + (f" whose blur disc at the start is at least {CLOSED_FORM_MIN_BLUR_PX:g} px" if CLOSED_FORM_MIN_BLUR_PX > 0 else "")
        + ", fixed lens samples for the others, so `closed_form`, "
        "`samples` or `mixed`, with the count `closed_form_pixels` and the fixed `lens_samples` per pixel of the "
        "others (chosen from the start's blur; 0 when every pixel is in closed form), and under "
        "`--psf auto` the `kernel_selection` test (`lr_statistic`, `p_value`, `delta_bic`, the disc-only fit's "
        "lens values); `held_out` (pixels kept out of the fit, the mean Huber cost of their residuals for the "
        "refinement and for the corner fit's lens and poses) and `kept`: `photometric` where the refinement "
        "predicts them better and `corner_check` does not reject it, then the top-level lens values and σ are the "
        "photometric fit's; `corner fit` otherwise, then they stay the corner fit's and the refinement's values "
        "are in `refined` and `refined_sigma`, and `rejected_because` says why (also on stderr). `corner_check`: "
        "the corners, held out of the photometric fit, predicted by its lens with each view's pose refitted "
        "(`refined_px`, RMS per corner) against the corner fit's k-fold held-out RMS (`start_px`; its own RMS "
        "where `start_is_held_out` is false), kept up to `limit_px`. `free`: the stored lens parameters the "
        "refinement moved (those the corner fit determined, each within 10 of its σ; `at_bound`: those that ended "
        "at that bound, then the corner fit is kept; `bounds`: per bounded parameter in CALIB.json's units its "
        "`start`, the bound's ends `low` and `high`, the `refined` value and `at_bound`, so which parameter hit "
        "which bound); per-view `levels` add the "
        "illumination gradient `gain_x`, `gain_y`; `levels` and `vignetting` are written whether kept or not (the "
        "refinement's exposure, which `tiltfit report` draws the residual image with). "
        "`sigma_model`: the error model of the refinement's σ "
        "(`refined_sigma`, and the top-level σ of the lens values it moved where it is kept): `views` (per-view "
        "cluster-robust as the corner fit's, each view's pose, levels and illumination gradient profiled out, never "
        "below the textbook σ; `design_effect`, `ratio_min`, `ratio_max`, `n_views`) or `tiles` (a sandwich over "
        "blur-disc tiles, where the per-view covariance cannot be formed: one view, or a singular one); a lens "
        "parameter `at_bound` is held out of it (σ 0).", "",
    ]


def _uncertainty_lines() -> list:
    """The CALIB-file paragraph of the σ, the covariance and cross-validation."""
    return [
        "Uncertainty: `sigma` is one standard deviation under the error model named in `sigma_model.name`: "
        "`views` (default; corner and blur errors may be correlated within a view, as a detector's bias with blur, "
        "the board's shape or a model misfit make them: per-view cluster-robust covariance with the poses profiled "
        "out and the CR2 small-sample correction, never below the classical covariance; `design_effect` is the "
        "globals' average variance ratio to the classical one; each pose's own part comes from a random affine "
        "error of each view's corners estimated from the residuals, `view_error_px` its RMS length at a corner) or "
        "`classical` (independent residuals). `sigma_model.model_choice` (after an automatic choice of distortion "
        "terms or board shape): the part of the σ of the focal length and principal point (`focal_px`, "
        "`principal_point_px`) from the models the held-out views could not tell apart, with their `weights`; "
        "it is in `sigma` and `intrinsics_covariance`. `sigma_classical` holds the classical σ of the same keys. "
        "`intrinsics_covariance` (`names`: focal_px, cx_px, cy_px, k1 … k6, theta_L_deg, tilt_axis_deg; `matrix`: "
        "symmetric, positive semi-definite, finite, no σ above 1e6, else the file is refused) is what `tiltfit "
        "compare` reads; both project through the full fitted lens (tilt, tilt axis, the distortion's centre); "
        "`projection_uncertainty` gives σ of the projection across the image (px, sqrt(σx² + σy²), the part "
        "a rotation of the camera frame explains removed; the same at every depth): `median_px`, `worst_px` and "
        "the map `sigma_px` on `grid_x_px` × `grid_y_px`. After `--cross-validate K`: `cross_validation` "
        "(`groups` of images, per pair `median_px`, `worst_px`, `predicted_median_px`, `predicted_worst_px`, "
        "`rms_ratio`, `consistent`, `verdict`).", "",
    ]


def _json_lines() -> list:
    """What holds for every JSON file."""
    return [
        "## Every JSON file", "",
        f"UTF-8 (UTF-16/32, other encodings and image bytes are refused by name), nested at most {MAX_JSON_DEPTH} "
        "levels, numbers finite. Each refusal is one line `tiltfit: <file>: <field>: <problem>`, exit status 2; "
        "an interrupt prints `tiltfit: interrupted`, exit status 130. Outputs are written atomically with "
        "permissions 0666 minus the umask.", "",
    ]


def target_schema() -> dict:
    edges = {"type": "array", "items": {"type": "number", "minimum": -target.MAX_MM, "maximum": target.MAX_MM},
             "minItems": 3, "maxItems": target.MAX_EDGES}
    pair = {"type": "array", "items": {"type": "integer"}, "minItems": 2, "maxItems": 2}
    common = {"units": {"const": "mm"}, "dark_cell": pair,
              "margin": {"type": "number", "minimum": 0, "maximum": target.MAX_MM},
              "inverted": {"type": "boolean"}, "name": {"type": "string"}, "description": {"type": "string"}}
    checkerboard = {"type": "object",
                    "properties": {"type": {"const": "checkerboard"}, "x_edges": edges, "y_edges": edges, **common},
                    "required": ["type", "x_edges", "y_edges"], "additionalProperties": False}
    side = {"type": "integer", "minimum": 2, "maximum": target.MAX_EDGES - 1}
    charuco = {"type": "object",
               "properties": {"type": {"const": "charuco"},
                              "dictionary": {"enum": target.aruco_dictionaries()},
                              "squares": {"type": "array", "items": side, "minItems": 2, "maxItems": 2},
                              "square_mm": {"type": "number", "exclusiveMinimum": 0, "maximum": target.MAX_MM},
                              "marker_mm": {"type": "number", "exclusiveMinimum": 0, "maximum": target.MAX_MM},
                              **common},
               "required": ["type", "dictionary", "squares", "square_mm", "marker_mm"], "additionalProperties": False}
    return {"$schema": SCHEMA_DIALECT, "title": "tiltfit target file", "oneOf": [checkerboard, charuco]}


def det_schema() -> dict:
    side = {"type": "integer", "minimum": 1, "maximum": detfile.MAX_IMAGE_SIDE}
    corner = {"oneOf": [{"type": "null"}, {"type": "array", "items": {"type": "number"}, "minItems": 2,
                                           "maxItems": 2}]}
    return {"$schema": SCHEMA_DIALECT, "title": "tiltfit detection file", "type": "object",
            "properties": {"image_size_px": {"type": "array", "items": side, "minItems": 2, "maxItems": 2},
                           "corners_px": {"type": "array", "items": corner},
                           "blur_px": {"type": "array", "items": {"oneOf": [{"type": "null"},
                                                                            {"type": "number", "minimum": 0}]}},
                           "grid_found": {"type": "boolean"},
                           "format_version": {"type": "integer", "minimum": 1,
                                              "maximum": detfile.DET_FORMAT_VERSION}},
            "required": ["image_size_px", "corners_px", "blur_px"]}


def build() -> dict[str, str]:
    """{path relative to docs/: content} of every generated file."""
    head = ("# File formats\n\n"
            "Generated by `python -m tiltfit.files.formats` from the validators' own declarations; do not edit by hand "
            "(tests fail when this file and the code disagree). Conventions (frames, units, pixels): "
            "[conventions.md](conventions.md).\n\n")
    schemas = {"scene": scene_schema(), "target": target_schema(), "det": det_schema()}
    out = {"file_formats.md": head + scene_reference() + "\n" + calibration_reference()}
    for name, schema in schemas.items():
        out[f"schemas/{name}.schema.json"] = json.dumps(schema, indent=1, ensure_ascii=False) + "\n"
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m tiltfit.files.formats", description=__doc__.splitlines()[0])
    ap.add_argument("--check", action="store_true", help="exit 1 when the committed files are out of date")
    args = ap.parse_args(argv)
    stale = []
    for rel, text in build().items():
        path = os.path.join(DOCS, rel)
        current = open(path, encoding="utf-8").read() if os.path.isfile(path) else None
        if current != text:
            stale.append(rel)
            if not args.check:
                os.makedirs(os.path.dirname(path), exist_ok=True)
                with open(path, "w", encoding="utf-8") as f:
                    f.write(text)
    if args.check and stale:
        print("out of date (run python -m tiltfit.files.formats): " + ", ".join(stale), file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
