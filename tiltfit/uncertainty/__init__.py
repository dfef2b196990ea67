"""How far a calibration can be trusted: parameter and projection covariances (`covariance`) and two
calibrations of one camera compared (`compare`)."""
