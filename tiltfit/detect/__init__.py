"""Finding the target in an image: chessboard saddles and grid growth (`chessboard`), ChArUco boards
(`charuco`), OpenCV's corners as a peer (`opencv`), blur widths at each corner (`blur`) and the image helpers
they share (`imaging`)."""
