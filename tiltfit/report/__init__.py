"""What a user looks at: the calibration report's plots (`plots`), each photo beside its rendering
(`real_vs_rendered`) and CG composited into calibrated photos (`composite`)."""
