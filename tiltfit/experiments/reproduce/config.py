"""What a run of the experiment is: its size (`RunConfig`), the lens states, the simulated truth (a) and the
set values, and what every stage shares: renders of the boxes scene, sensor noise, 8-bit images, seeds."""
from __future__ import annotations

import math
import time
import zlib
from dataclasses import dataclass, replace

import numpy as np
import torch
from renderer import write_image
from renderer import render
from renderer.cameras.sensor import SensorResponse

from ..scenes import Lens, Sensor, boxes_scene
from camio.progress import RunLog

NOT_RUN = "not run"  # a table cell of a stage that was skipped (RunConfig.calibrate False) or failed


@dataclass(frozen=True)
class LensState:
    """One of the paper's three lens states (Fig. 10): a label and the tilt set on the lens scale."""

    label: str
    theta_L_set_deg: float

LENS_STATES = (LensState("a", 0.0), LensState("b", 5.0), LensState("c", -5.0))

@dataclass(frozen=True)
class RunConfig:
    """How much work a run does.

    Attributes:
        downscale: pixel binning of the boxes images (16: 342 x 228; 32: 171 x 114).
        spp_capture: samples per pixel of the simulated photographs.
        spp_cg: samples per pixel of the CG re-renders.
        spp_sweep: CG samples per pixel of the speed–accuracy sweep.
        step_px: spacing of the profile samples along the lines, pixels.
        seed: base seed of every render and noise draw.
        sampler: the renderer's sample pattern.
        target_downscale: pixel binning of the target photographs (detection wants more pixels; 8: 684 x 456,
            1: the paper's 5472 x 3648).
        target_views: target views per lens state (the first of TARGET_VIEWS).
        target_method: how `tiltfit.experiments.synth` renders the target (`analytic` or `renderer`).
        photometric_pixels, photometric_lens_samples: pixels per view and fixed lens samples of the
            photometric refinement (0 pixels: skip it).
        device: torch device of the boxes renders (`cpu` or `cuda`); the fits run on the CPU.
        calibrate: False skips the target photographs and the calibration, stages (b) and (c).
    """

    downscale: int = 16
    spp_capture: int = 64
    spp_cg: int = 32
    spp_sweep: tuple[int, ...] = (1, 2, 4, 8, 16, 32, 64)
    step_px: float = 0.5
    seed: int = 2016
    sampler: str = "sobol"
    target_downscale: int = 8
    target_views: int = 5
    target_method: str = "renderer"
    photometric_pixels: int = 2000
    photometric_lens_samples: int = 64
    device: str = "cpu"
    calibrate: bool = True

    @staticmethod
    def full() -> "RunConfig":
        return RunConfig()

    @staticmethod
    def quick() -> "RunConfig":
        """About a minute on two cores: small images, few samples."""
        # The target photographs keep the full run's size and views: Table 1 is the experiment's result and
        # its test holds the joint fit to 0.05°, which 3 views at 1/16 do not reach (0.1° at −5°). They come
        # from the noise-free analytic model: ray traced at 16 spp their Monte Carlo noise put the photometric
        # θL 0.12° off.
        return RunConfig(downscale=32, spp_capture=16, spp_cg=16, spp_sweep=(1, 4, 16), target_downscale=8,
                         target_views=5, target_method="analytic", photometric_pixels=800,
                         photometric_lens_samples=32)


@dataclass(frozen=True)
class SimulatedCamera:
    """The simulated camera: its true lens and what its sensor does to an image. Never shown to the fit.

    Attributes:
        untilted: the true lens untilted, with its sensor (`renderer.Lens.paper()`: the paper's stage-1 values
            on an EOS 6D).
        tilt_gain, tilt_offset_deg: the true tilt for a set tilt θs ≠ 0 is gain · θs + offset (a tilt scale
            that is slightly off); the 0 detent is exact.
        full_well: photo-electrons at linear value 1 per output pixel (shot noise, Poisson as Gaussian).
        read_noise: standard deviation of the read noise, linear units.
        vignetting: fall-off 1 − v r² with r the distance from the image centre, 1 at the corners.
    """

    untilted: Lens = Lens.paper()
    tilt_gain: float = 0.98
    tilt_offset_deg: float = -0.25
    full_well: float = 4000.0
    read_noise: float = 0.002
    vignetting: float = 0.05

    @property
    def sensor(self) -> Sensor:
        return self.untilted.sensor

    @property
    def f_mm(self) -> float:
        """Focal length of the true thin lens (1/f = 1/w + 1/U0)."""
        return self.untilted.f

    def theta_L_deg(self, theta_L_set_deg: float) -> float:
        """The true lens tilt for a tilt set on the lens scale, degrees."""
        if theta_L_set_deg == 0:
            return 0.0
        return self.tilt_gain * theta_L_set_deg + self.tilt_offset_deg

    def lens(self, theta_L_set_deg: float) -> Lens:
        """The true lens state: the lens (focal length f, sensor at w) tilted about its centre, so the
        focus distance follows the hinge rule U = f w / (w cos θL − f) (`Lens.from_tilt`)."""
        lens = self.untilted
        return Lens.from_tilt(lens.w, self.f_mm, math.radians(self.theta_L_deg(theta_L_set_deg)), lens.d,
                              sensor=lens.sensor)

    @property
    def response(self) -> SensorResponse:
        """The sensor's response (`renderer.cameras.sensor`): vignetting, shot and read noise, 8-bit sRGB."""
        return SensorResponse(vignetting=self.vignetting, read_noise=self.read_noise, full_well=self.full_well,
                              encoding="srgb8")

    def expose(self, radiance, rng) -> np.ndarray:
        """What the camera writes for a linear image: vignetting, shot + read noise, 8-bit sRGB.

        Args:
            radiance: (H, W, 3) linear float image as rendered (numpy, or a tensor exposed on its device).
            rng: the noise source (np.random.Generator; a torch.Generator on the device for a tensor).
        Returns:
            (H, W, 3) uint8 sRGB image.
        """
        return self.response.expose(radiance, rng)

    def expose_cg(self, radiance) -> np.ndarray:
        """A CG render written as the camera writes its photos, noise excepted: (H, W, 3) uint8 sRGB. The CG
        carries the lens's vignetting too: a user compositing CG into the photo flat-fields both alike."""
        return replace(self.response, read_noise=0.0, full_well=None).expose(radiance)

@dataclass(frozen=True)
class SetValues:
    """What the photographer knows without calibrating the blur.

    Attributes:
        nominal: w from a geometry-only calibration, rounded (55 mm); U read off the focus scale (600 mm); d the
            nominal aperture, focal length / f-number = 45 mm / 2.8 (16.07 mm).
    The tilt is the one set on the tilt scale, and U is taken to stay put when the lens is tilted.
    """

    nominal: Lens = Lens(55.0, 600.0, 45.0 / 2.8)

    def lens(self, theta_L_set_deg: float) -> Lens:
        n = self.nominal
        return Lens.from_theta_L(n.w, n.U, n.d, math.radians(theta_L_set_deg))


def run_log(enabled: bool = True) -> RunLog:
    return RunLog("reproduce", enabled)

def render_boxes(lens: Lens, cfg: RunConfig, spp: int, seed: int):
    """Render the boxes scene through `lens`; returns the (H, W, 3) linear image and the render time, s.

    The image is a numpy array from a CPU render, and a tensor left on the device from a GPU render: the
    camera exposes it there (`SimulatedCamera.expose`): numpy takes 3 s a 5472 x 3648 photo on these cores
    (benchmarks/results/batch_io.md), as long as a 32-spp GPU render of it.
    """
    scene = boxes_scene(lens, downscale=cfg.downscale, spp=spp, sampler=cfg.sampler)
    t = time.perf_counter()
    image = render(scene, spp=spp, seed=seed, device=cfg.device).image
    if image.device.type == "cpu":
        image = image.numpy()
    else:
        torch.cuda.synchronize(image.device)  # the render's time, not its launch
    return image, time.perf_counter() - t

def noise_source(radiance, seed: int):
    """The sensor-noise generator for an image: numpy's for a numpy image, torch's on the image's device for
    a tensor (another draw for the same seed)."""
    if isinstance(radiance, torch.Tensor):
        return torch.Generator(radiance.device).manual_seed(seed)
    return np.random.default_rng(seed)

def save_png(path: str, image_u8: np.ndarray) -> None:
    """Write an 8-bit sRGB image exactly (`renderer.write_image` stores uint8 levels unchanged)."""
    write_image(path, np.asarray(image_u8, dtype=np.uint8), encoding="srgb")

def seed_for(cfg: RunConfig, *keys) -> int:
    """A distinct, reproducible seed per render and noise draw (CRC-32 of the keys, not Python's hash)."""
    return zlib.crc32(repr((cfg.seed,) + keys).encode()) & 0x7FFFFFFF
