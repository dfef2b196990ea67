"""Fitting the camera: the model and its residuals (`model`), the least-squares problem (`problem`) and fit
(`fit`), its starting point (`start`), the calibration as a sequence of stages (`flow`), calibration from
photographs (`photos`), the blur-view screen (`blur_views`) and where a tilted lens centres its distortion
(`distortion_centre`)."""
