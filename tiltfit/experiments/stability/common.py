"""What every stability study shares: the run size (`StabilityConfig`), the simulated lens, the `Study` record
each sweep returns, and the figure helper."""
from __future__ import annotations

from dataclasses import dataclass, field

from renderer import Lens

@dataclass(frozen=True)
class StabilityConfig:
    """How much work a run does (defaults: the full run).

    Attributes:
        detector_ratios: blur diameter / projected square of the detector sweep (a).
        detector_poses: how many of DETECTOR_POSES are rendered per ratio.
        detector_downscale: pixel binning of the EOS 6D sensor for (a) [8: 684 × 456].
        tilts_deg: lens tilts θL of the two-stage vs joint sweep (b), degrees.
        tilt_downscale: binning of the sensor whose size and pitch (b)'s observations use.
        tilt_noise_px: corner and blur noise of (b)'s observations, pixels (one σ).
        coverage_theta_F_deg: θF of the coverage sweep (c), degrees.
        coverage_downscale, coverage_spp: size and samples per pixel of (c)'s renders.
        singular_eps: a3* − a3 of the inverted-perspective sweep (d), scene units (0: at the singular depth;
            negative: beyond it).
        srgb_ratios: blur / projected square of the sRGB sweep (e).
        noise_levels: standard deviations of the Gaussian noise added to the linear target images before
            8-bit sRGB quantisation (e); the sRGB-mistake calibration runs at the first.
        noise_views: target views (the first of `reproduce.TARGET_VIEWS`) per calibration (e).
        noise_downscale: binning of (e)'s target photographs.
        seed: base seed of every noise draw.
    """

    detector_ratios: tuple[float, ...] = (0.0, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 1.0)
    detector_poses: int = 3
    detector_downscale: int = 8
    tilts_deg: tuple[float, ...] = (0.5, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0, 9.0, 10.0, -5.0)
    tilt_downscale: int = 8
    tilt_noise_px: float = 0.05
    coverage_theta_F_deg: tuple[float, ...] = (0.0, 20.0, 40.0, 60.0, 70.0, 75.0, 77.0, 78.0, 79.0, 80.0, 82.0,
                                              84.0, 86.0, 88.0, 89.0)
    coverage_downscale: int = 64
    coverage_spp: int = 16
    singular_eps: tuple[float, ...] = (4.0, 2.0, 1.0, 0.5, 0.25, 0.1, 1e-2, 1e-3, 1e-4, 1e-6, 1e-9, 0.0, -0.5)
    srgb_ratios: tuple[float, ...] = (0.025, 0.05, 0.075, 0.1, 0.15, 0.25, 0.4, 0.6)
    noise_levels: tuple[float, ...] = (0.002, 0.005, 0.01, 0.02, 0.04, 0.08)
    noise_views: int = 5
    noise_downscale: int = 12
    seed: int = 2017

    @staticmethod
    def full() -> "StabilityConfig":
        return StabilityConfig()

    @staticmethod
    def quick() -> "StabilityConfig":
        """About a minute on two cores: few points per sweep, small images."""
        return StabilityConfig(detector_ratios=(0.1, 0.3, 0.5, 0.7, 0.9), detector_poses=1, detector_downscale=12,
                               tilts_deg=(0.5, 2.0, 5.0, 10.0, -5.0),
                               coverage_theta_F_deg=(0.0, 40.0, 70.0, 77.0, 78.0, 80.0, 84.0, 88.0),
                               coverage_spp=4, singular_eps=(4.0, 1.0, 0.25, 1e-2, 1e-6, 0.0, -0.5),
                               srgb_ratios=(0.05, 0.5), noise_levels=(0.002, 0.04),
                               noise_views=3, noise_downscale=16)


#: The simulated camera's lens (`renderer.Lens.paper()`, as `tiltfit.experiments.reproduce.SimulatedCamera`), mm.
W_MM, U0_MM, D_MM = Lens.paper().w, Lens.paper().U, Lens.paper().d
F_MM = Lens.paper().f


@dataclass
class Study:
    """One sweep's outcome.

    Attributes:
        name: file stem of its outputs (`name`.json, .csv, .png).
        title: heading in stability.md.
        rows: the table (CSV and Markdown), one dict per sweep point.
        findings: sentences, each stating one finding with its number.
        data: further numbers for the JSON (closed forms, thresholds).
        figure: the matplotlib Figure, or None.
        runtime_s: seconds the sweep took.
    """

    name: str
    title: str
    rows: list
    findings: list
    data: dict = field(default_factory=dict)
    figure: object = None
    runtime_s: float = 0.0


def subplots_row(ncols: int, width: float = 4.2, height: float = 3.2):
    """A constrained-layout Figure with one row of `ncols` axes (`width` × `height` inches each); (fig, axes)."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width * ncols, height), layout="constrained")
    return fig, fig.subplots(1, ncols, squeeze=False)[0]
