"""The `tiltfit` command: `main` (detect, calibrate, report, export, compare, reproduce, stability) and
`target` (`tiltfit target design|print`)."""
