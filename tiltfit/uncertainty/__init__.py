"""How far a calibration can be trusted: parameter and projection covariances (`covariance`, with the fit's
per-view columns in `columns`) and two calibrations of one camera compared (`compare`)."""
