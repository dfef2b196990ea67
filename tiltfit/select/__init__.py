"""Which model the data support: held-out reprojection error and the distortion model it picks
(`held_out`), the nested-model test (`stats`), the blur and tilt decisions (`nested`) and the board shape (`board`)."""
