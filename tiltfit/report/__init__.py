"""What a user looks at.

Modules:
    plots             `tiltfit report`'s plots (`write_report`: residuals, blur against depth, coverage, projection σ)
    summary           its report.md (the calibration in numbers, each rounded to its σ: `with_sigma`)
    photometric       the photometric refinement's record and each view's residual image (photo − model)
    real_vs_rendered  each photo beside the target rendered through the calibration
    composite         CG composited into calibrated photos
"""
