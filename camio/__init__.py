"""What both `renderer` and `tiltfit` use and neither owns: files written atomically and images read and
written through OpenImageIO (`files`), the input checks every reader shares (`checks`), progress lines
(`progress`) and Ctrl-C held over steps that must not be cut short (`interrupts`)."""
