"""The calibration target.

Modules:
    layout     the board's layout (`Target`: rows, columns, non-uniform spacing; `CharucoTarget`: ArUco markers),
               its target file (`load_target`, `target_from_dict`) and its checks
    design     designed targets whose rows project equally spaced in a chosen view (`design_target`)
    raster     images of the board: exact dark fractions (`rasterise`), print renders, textures
    printable  the printable PNG and PDF at true size with a scale bar (`write_printable`)
    shape      the printed board's fitted shape (flat, warped or free)
"""
