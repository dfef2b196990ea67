"""Finding the target in an image.

Checkerboards (`chessboard`: the pipeline and its public names), by stage: saddle candidates (`saddles`), grid growth
(`grid`), sub-pixel refinement and completion (`refine`), indexing (`indexing`), checks against the target file
(`checks`). ChArUco boards (`charuco`: the pipeline), with the lattice placed by the markers' pattern
(`charuco_lattice`) and the model fit under heavy blur (`charuco_model`). The `Detection` record and its JSON file
(`detection`), blur widths at each corner (`blur`, fitted on the pixel bands of `blur_bands`), OpenCV's corners as
a peer (`opencv`) and the image helpers they share (`imaging`)."""
