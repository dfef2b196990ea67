"""The calibration target: the board's layout (`layout`: rows, columns, non-uniform spacing, ChArUco
markers, printing) and the printed board's fitted shape (`shape`: flat, warped or free)."""
