"""What every camera shares: the pose, the pixel-to-screen mapping and the ray-generation call.

A camera = pose (`CameraTransform`) + projection or lens (the subclass) + sensor mapping (`Screen`).
Every camera answers one call, `generate_rays(uv_px, lens_uv)`: pixel positions and lens samples in,
world-frame rays out. The caller owns the random numbers.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from renderer.core.params import SceneError
from renderer.core.rays import Rays
from renderer.core.transforms import CameraTransform
from .distortion import _solve2, distort_about_axis_jacobians, distort_jacobian
from .projection import image_centre_px, normalised_from_pixels, pixels_from_normalised, project_pinhole

#: `Camera.undistort_pixels` keeps a map of the inverse distortion, nodes every this many pixels, for calls with at
#: least `UNDISTORTION_MAP_MIN_POINTS` pixels (a render's), to start Newton's method near the root.
UNDISTORTION_MAP_STEP_PX = 8
UNDISTORTION_MAP_MIN_POINTS = 4096


@dataclass(frozen=True)
class Screen:
    """Maps pixels to points on a plane z = distance in the camera frame.

    Pixel (x, y), with (0, 0) the centre of the top-left pixel, lands at
    ((x − cx) · size_x / W, (y − cy) · size_y / H, distance), where (cx, cy) is the principal point,
    by default ((W − 1)/2, (H − 1)/2).

    Attributes:
        width_px, height_px: image size in pixels.
        size: (size_x, size_y) screen extent in scene units (W and H pixel pitches).
        distance: screen distance along the camera z axis, scene units (q3 of the papers, or w); a float or a
            0-dim tensor (gradients then reach it).
        principal_point_px: optional (cx, cy).
    """

    width_px: int
    height_px: int
    size: tuple[float, float]
    distance: float
    principal_point_px: tuple[float, float] | None = None

    @property
    def pitch(self) -> tuple[float, float]:
        return self.size[0] / self.width_px, self.size[1] / self.height_px

    @property
    def center_px(self) -> tuple[float, float]:
        if self.principal_point_px is not None:
            return self.principal_point_px
        return image_centre_px(self.width_px, self.height_px)

    def to_plane(self, uv_px: torch.Tensor) -> torch.Tensor:
        """(..., 2) pixels -> (..., 3) points on the screen plane, camera frame."""
        return torch.stack(self.plane_rows(uv_px), dim=-1)

    def plane_rows(self, uv_px: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """`to_plane` as its three (...,) components x, y, z (for cameras that build rays per component)."""
        x, y = self.plane_xy(uv_px)
        # `distance` may be a tensor (the thin lens's w, fitted): broadcast, don't copy it into a fill.
        return x, y, torch.zeros_like(x) + self.distance

    def plane_xy(self, uv_px: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The x, y components of `plane_rows` (z is `distance` everywhere)."""
        (cx, cy), (px, py) = self.center_px, self.pitch
        return (uv_px[..., 0] - cx) * px, (uv_px[..., 1] - cy) * py

    def to_pixels(self, p_plane: torch.Tensor) -> torch.Tensor:
        """Inverse of `to_plane`: (..., 2) plane coordinates (x, y) -> pixels."""
        (cx, cy), (px, py) = self.center_px, self.pitch
        return torch.stack([p_plane[..., 0] / px + cx, p_plane[..., 1] / py + cy], dim=-1)

    @staticmethod
    def from_fov(width_px: int, height_px: int, fov_deg: float, distance: float = 1.0) -> "Screen":
        """Screen whose horizontal field of view is fov_deg, with square pixels."""
        sx = 2.0 * distance * math.tan(math.radians(fov_deg) / 2.0)
        return Screen(width_px, height_px, (sx, sx * height_px / width_px), distance)


def screen_from_config(path: str, cfg: dict, width: int, height: int) -> Screen:
    """The screen of `screen_size` (or `fov_deg`) at `screen_distance`, for cameras that use SCREEN_PARAMS."""
    q3 = cfg["screen_distance"]
    if q3 <= 0:
        raise SceneError(f"{path}.screen_distance: expected a positive distance, got {q3}")
    if cfg.get("screen_size") is not None:
        sx, sy = cfg["screen_size"]
        if sx <= 0 or sy <= 0:
            raise SceneError(f"{path}.screen_size: expected positive sizes, got {[sx, sy]}")
        return Screen(width, height, (sx, sy), q3)
    if cfg.get("fov_deg") is not None:
        if not 0 < cfg["fov_deg"] < 180:
            raise SceneError(f"{path}.fov_deg: expected an angle in (0, 180), got {cfg['fov_deg']}")
        return Screen.from_fov(width, height, cfg["fov_deg"], q3)
    raise SceneError(f"{path}: give screen_size or fov_deg")


class Camera:
    """Base class: subclasses implement `rays_in_camera`; the pose is applied once here.

    Attributes:
        transform: the pose.
        screen: the sensor/screen mapping of pixels (its `width_px`, `height_px` set the image size).
        uses_lens_samples: whether `lens_uv` affects the rays (False for pinhole-like projections).
    """

    uses_lens_samples = False
    distortion = None  # a `distortion.BrownConrady` of the lens, set from the scene file's camera.distortion

    def __init__(self, transform: CameraTransform, screen: Screen):
        self.transform = transform
        self.screen = screen

    @property
    def focal_px(self):
        """(f_x, f_y): the screen distance in pixels along each axis (a tensor where the distance is one)."""
        px, py = self.screen.pitch
        return self.screen.distance / px, self.screen.distance / py

    def _normalised(self, uv_px: torch.Tensor) -> torch.Tensor:
        """(..., 2) pixels -> (..., 2) normalised image coordinates (x_s, y_s) / distance about the principal point."""
        return normalised_from_pixels(uv_px, self.focal_px, self.screen.center_px)

    def _from_normalised(self, xy: torch.Tensor) -> torch.Tensor:
        return pixels_from_normalised(xy, self.focal_px, self.screen.center_px)

    def undistort_pixels(self, uv_px: torch.Tensor,
                         start_px: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Pixels of the distorted image -> ((..., 2) pixels of the ideal, distortion-free camera, (...,) valid).

        Identity without `distortion`; invalid where the distortion cannot be inverted. `start_px`: (..., 2) ideal
        pixels near the answer where Newton's method starts (the root is the same, reached in fewer steps) [an
        interpolated map of the inverse where the camera's numbers are plain, else the pixels themselves].
        """
        if self.distortion is None or self.distortion.is_identity:
            return uv_px, torch.ones(uv_px.shape[:-1], dtype=torch.bool, device=uv_px.device)
        start = skip = None
        if start_px is not None:
            start = self._normalised(start_px)
        elif self._plain_distortion() and uv_px.shape[:-1].numel() >= UNDISTORTION_MAP_MIN_POINTS:
            start, skip = self._undistortion_start(uv_px)
        xy = self.distortion.undistort(self._normalised(uv_px), start, skip)
        ok = torch.isfinite(xy).all(-1)
        return torch.where(ok[..., None], self._from_normalised(torch.nan_to_num(xy)), uv_px), ok

    def undistort_pixels_from(self, uv_px: torch.Tensor, ideal_px: torch.Tensor,
                              valid: torch.Tensor) -> torch.Tensor:
        """`undistort_pixels(uv_px)[0]` as a function of the camera's parameters, given its values `ideal_px` and
        `valid` (computed without derivatives): one Newton step from them, so the same numbers to rounding, whose
        derivatives are the implicit function's, dx = J⁻¹ (dx_d − ∂D) with J = ∂D/∂x at the root (`distortion.
        undistort` ends the same way). The Newton iterations then run once, not under forward-mode tangents.

        Args:
            uv_px: (..., 2) pixels of the distorted image; ideal_px, valid: what `undistort_pixels` returned for
                them (pixels where `valid` is False stay `uv_px`, as there).
        Returns:
            (..., 2) pixels of the ideal, distortion-free camera.
        """
        if self.distortion is None or self.distortion.is_identity:
            return uv_px
        xy0 = self._normalised(ideal_px)
        k, R = self.distortion.coefficients, self.distortion.camera_from_lens
        with torch.no_grad():
            x, kd = xy0.detach(), (k.detach() if isinstance(k, torch.Tensor) else k)
            J = distort_jacobian(x, kd) if R is None else distort_about_axis_jacobians(
                x, kd, R.detach() if isinstance(R, torch.Tensor) else R)[1]
            det = J[..., 0, 0] * J[..., 1, 1] - J[..., 0, 1] * J[..., 1, 0]
        step = _solve2(J, self.distortion.distort(xy0) - self._normalised(uv_px))
        ok = valid & (det != 0)
        return torch.where(ok[..., None], self._from_normalised(xy0 - torch.where(ok[..., None], step, 0.0)), uv_px)

    def undistort_pixels_jacobian(self, uv_px: torch.Tensor, ideal_px: torch.Tensor,
                                  valid: torch.Tensor) -> torch.Tensor:
        """(..., 2, 4) derivatives of `undistort_pixels(uv_px)[0]` by the focal lengths and the principal point
        (f_x, f_y, c_x, c_y; pixels), given its values `ideal_px` and `valid`, for a distortion about the
        principal point with fixed coefficients (`distortion.camera_from_lens` None): at the root x of
        D(x) = n = (uv − c) / f, dx = J⁻¹ dn with J = ∂D/∂x (implicit function), and ideal = f x + c. Zero where
        `valid` is False (those pixels stay `uv_px`).

        Args:
            uv_px: (..., 2) pixels of the distorted image; ideal_px, valid: what `undistort_pixels` returned for them.
        Returns:
            (..., 2, 4) derivatives of the ideal pixels by (f_x, f_y, c_x, c_y).
        """
        if self.distortion is None or self.distortion.camera_from_lens is not None:
            raise ValueError("undistort_pixels_jacobian: needs a distortion about the principal point (none, or one "
                             "about the lens axis, given)")
        f = torch.stack([torch.as_tensor(t).to(uv_px) for t in self.focal_px])
        c = torch.stack([torch.as_tensor(t).to(uv_px) for t in self.screen.center_px])
        x, n = (ideal_px - c) / f, (uv_px - c) / f
        J = distort_jacobian(x, self.distortion.coefficients)
        # dn/d(f, c): n_i = (uv_i − c_i) / f_i, so ∂n_i/∂f_i = −n_i / f_i and ∂n_i/∂c_i = −1 / f_i.
        eye = torch.eye(2, dtype=uv_px.dtype, device=uv_px.device)
        dn = torch.cat([-(n / f)[..., None] * eye,
                        (-1.0 / f)[:, None] * eye.expand(n.shape[:-1] + (2, 2))], -1)
        dx = _solve2(J[..., None, :, :], dn.transpose(-1, -2)).transpose(-1, -2)  # J⁻¹ dn, column by column
        # ideal_i = f_i x_i + c_i: ∂/∂f_i = x_i + f_i ∂x_i/∂f_i, ∂/∂c_i = 1 + f_i ∂x_i/∂c_i (and the cross
        # terms).
        d_ideal = f[:, None] * dx + torch.cat([x[..., None] * eye, eye.expand(x.shape[:-1] + (2, 2))], -1)
        ok = valid & torch.isfinite(d_ideal).all(-1).all(-1)
        return torch.where(ok[..., None, None], d_ideal, 0.0)

    def _plain_distortion(self) -> bool:
        """Whether the distortion and the pixel mapping are plain numbers (no gradient wanted through them), so
        that a map of the inverse can be kept with the camera."""
        c, R = self.distortion.coefficients, self.distortion.camera_from_lens
        numbers = (*self.focal_px, *self.screen.center_px)
        return not isinstance(c, torch.Tensor) and not isinstance(R, torch.Tensor) and \
            not any(isinstance(v, torch.Tensor) for v in numbers)

    def _undistortion_start(self, uv_px: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Where `undistort`'s Newton steps start for pixels `uv_px`: the exact inverse at the nodes of a grid
        every `UNDISTORTION_MAP_STEP_PX` pixels over the image (computed once per camera), interpolated
        bilinearly; NaN (start from the pixel itself) next to a node without an inverse, and `skip` where all
        four nodes around the pixel have none (beyond where the distortion can be inverted). Newton then needs
        one or two steps instead of up to 20; the root it converges to is the same."""
        key = (self.distortion, self.focal_px, self.screen.center_px, self.width, self.height, uv_px.dtype,
               uv_px.device)
        cached = getattr(self, "_undistortion_map", None)
        if cached is None or cached[0] != key:
            step = UNDISTORTION_MAP_STEP_PX
            nx, ny = math.ceil(self.width / step) + 1, math.ceil(self.height / step) + 1
            gx = torch.arange(nx, dtype=uv_px.dtype, device=uv_px.device) * step - 0.5
            gy = torch.arange(ny, dtype=uv_px.dtype, device=uv_px.device) * step - 0.5
            nodes = torch.stack(torch.meshgrid(gx, gy, indexing="xy"), -1)  # (ny, nx, 2)
            inverse = self.distortion.undistort(self._normalised(nodes)).reshape(ny * nx, 2)
            # The nodes row by row, and each node's four corners of its cell side by side (x then y of the node,
            # its right, lower and lower-right neighbours): one row gathered a pixel.
            cells = torch.cat([inverse, inverse.roll(-1, 0), inverse.roll(-nx, 0), inverse.roll(-nx - 1, 0)], -1)
            cached = (key, (nx, ny), cells, torch.isfinite(cells).reshape(-1, 4, 2).all(-1).any(-1))
            self._undistortion_map = cached
        _, (nx, ny), cells, any_inverse = cached
        fx = ((uv_px[..., 0].detach() + 0.5) / UNDISTORTION_MAP_STEP_PX).clamp(0, nx - 1 - 1e-9)
        fy = ((uv_px[..., 1].detach() + 0.5) / UNDISTORTION_MAP_STEP_PX).clamp(0, ny - 1 - 1e-9)
        i0, j0 = fx.floor().long().clamp(max=nx - 2), fy.floor().long().clamp(max=ny - 2)
        ax, ay = (fx - i0)[..., None], (fy - j0)[..., None]
        cell = (j0 * nx + i0).reshape(-1)
        c00, c10, c01, c11 = cells.index_select(0, cell).reshape(uv_px.shape[:-1] + (4, 2)).unbind(-2)
        start = (1 - ay) * ((1 - ax) * c00 + ax * c10) + ay * ((1 - ax) * c01 + ax * c11)
        return start, ~any_inverse.index_select(0, cell).reshape(uv_px.shape[:-1])

    @property
    def width(self) -> int:
        return self.screen.width_px

    @property
    def height(self) -> int:
        return self.screen.height_px

    @classmethod
    def from_config(cls, path: str, cfg: dict, transform: CameraTransform, width: int, height: int) -> "Camera":
        """Build from a validated scene-file section; the default suits cameras defined by their screen alone."""
        return cls(transform, screen_from_config(path, cfg, width, height))

    def project_central(self, p_world: torch.Tensor) -> torch.Tensor:
        """(..., 3) world points -> (..., 2) pixels by central projection through the camera centre onto the
        screen (the pinhole's projection, and a thin lens's chief ray): `projection.project_pinhole`."""
        p_cam = self.transform.points_to_camera(p_world)
        if self.distortion is None or self.distortion.is_identity:
            return project_pinhole(p_cam, self.focal_px, self.screen.center_px)
        return project_pinhole(p_cam, self.focal_px, self.screen.center_px, self.distortion.coefficients,
                               self.distortion.camera_from_lens)

    def rays_in_camera(self, uv_px: torch.Tensor, lens_uv: torch.Tensor) -> Rays:
        """Rays in the camera frame for pixels (..., 2) and lens samples (..., 2) in [0, 1)²."""
        raise NotImplementedError

    def generate_rays(self, uv_px: torch.Tensor, lens_uv: torch.Tensor | None = None) -> Rays:
        """World-frame rays for pixel positions (..., 2) and lens samples (..., 2) in [0, 1)².

        Args:
            uv_px: (..., 2) float pixel positions (x = column, y = row), (0, 0) the top-left pixel centre.
            lens_uv: (..., 2) uniform samples for the aperture; ignored by cameras without a lens.
        Returns:
            Rays with (..., 3) origin, unit direction, (...,) valid mask and weight, world frame.
        """
        if lens_uv is None:
            lens_uv = torch.full_like(uv_px, 0.5)
        if self.distortion is None or self.distortion.is_identity:
            return self.transform.rays_to_world(self.rays_in_camera(uv_px, lens_uv))
        # The lens distorts: trace each pixel through its ideal (undistorted) position.
        ideal_px, ok = self.undistort_pixels(uv_px)
        rays = self.rays_in_camera(ideal_px, lens_uv)
        rays.valid = rays.valid & ok
        return self.transform.rays_to_world(rays)

    def project(self, p_world: torch.Tensor) -> torch.Tensor:
        """(..., 3) world points -> (..., 2) pixels, where the projection has a closed form."""
        raise NotImplementedError(f"{type(self).__name__} has no closed-form projection")
