"""Rigid transforms and camera poses (the transform kept apart from the projection, as in pbrt).

The one owner of rotations in both packages: look-at (`look_at_rotation`), axis-angle ↔ matrix (Rodrigues,
`axis_angle_to_matrix` / `matrix_to_axis_angle`), the camera pose (`CameraTransform`, with
`from_extrinsics` for tiltfit's X_cam = R X_world + T) and 4×4 placements for exporters
(`world_from_local_4x4`).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from renderer.core.rays import Rays, normalize


def look_at_rotation(position, look_at, up) -> torch.Tensor:
    """Rotation world_from_camera for a camera at `position` looking at `look_at`.

    The camera frame is x right, y down, z forward (OpenCV). `up` is the world direction that appears
    upwards in the image, so camera -y is the component of `up` orthogonal to the view direction.

    Returns:
        (3, 3) float64 matrix whose columns are the camera axes in world coordinates.
    """
    p = torch.as_tensor(position, dtype=torch.float64)
    z = normalize(torch.as_tensor(look_at, dtype=torch.float64) - p)
    u = torch.as_tensor(up, dtype=torch.float64)
    y = normalize(-(u - (u @ z) * z))
    if torch.linalg.vector_norm(y) < 1e-9:
        raise ValueError("camera.up is parallel to the viewing direction")
    x = torch.linalg.cross(y, z)
    return torch.stack([x, y, z], dim=1)


def world_from_local_4x4(R, t, scale=(1.0, 1.0, 1.0)) -> list[list[float]]:
    """The 4×4 world_from_local = [R · diag(scale) | t; 0 0 0 1] as nested lists of floats (float64), e.g. a
    Mitsuba `to_world`. R: (3, 3) rotation, columns the local axes in the world; t: (3,) local origin in the
    world; scale: (3,) stretch along the local axes. Arrays or tensors without gradients."""
    M = np.eye(4)
    M[:3, :3] = np.asarray(R, dtype=np.float64) * np.asarray(scale, dtype=np.float64)[None, :]
    M[:3, 3] = np.asarray(t, dtype=np.float64)
    return M.tolist()


def _skew(v: torch.Tensor) -> torch.Tensor:
    """(..., 3) vectors -> (..., 3, 3) cross-product matrices [v]×."""
    o = torch.zeros_like(v[..., 0])
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    return torch.stack([o, -z, y, z, o, -x, -y, x, o], dim=-1).reshape(v.shape[:-1] + (3, 3))


def axis_angle_to_matrix(rvec: torch.Tensor) -> torch.Tensor:
    """(..., 3) axis-angle vectors (radians) -> (..., 3, 3) rotation matrices (Rodrigues; smooth at 0).

    R = I + (sin θ / θ) K + ((1 − cos θ) / θ²) K²,  K = [rvec]×, θ = |rvec|; the series near θ = 0 keeps it
    differentiable there. Device and dtype follow `rvec`.
    """
    rvec = torch.as_tensor(rvec)
    theta2 = (rvec * rvec).sum(-1)[..., None, None]
    small = theta2 < 1e-8
    safe = torch.where(small, torch.ones_like(theta2), theta2)
    theta = torch.sqrt(safe)
    a = torch.where(small, 1.0 - theta2 / 6.0, torch.sin(theta) / theta)
    b = torch.where(small, 0.5 - theta2 / 24.0, (1.0 - torch.cos(theta)) / safe)
    K = _skew(rvec)
    eye = torch.eye(3, dtype=rvec.dtype, device=rvec.device).expand(K.shape)
    return eye + a * K + b * (K @ K)


def axis_angle_left_jacobian(rvec: torch.Tensor) -> torch.Tensor:
    """(..., 3) axis-angle vectors -> (..., 3, 3) left Jacobian J_l of the rotation exponential (smooth at 0).

    A change δr of the axis-angle vector turns R(r) by the small rotation J_l(r) δr applied on the left:
    R(r + δr) ≈ exp([J_l δr]×) R(r), so a rotated point moves by ∂(R X)/∂r = −[R X]× J_l(r). In closed form
    (Barfoot, "State Estimation for Robotics", 2017, eq. 7.86)
        J_l = I + ((1 − cos θ) / θ²) K + ((θ − sin θ) / θ³) K²,  K = [r]×, θ = |r|,
    with the Taylor series near θ = 0. Device and dtype follow `rvec`.
    """
    rvec = torch.as_tensor(rvec)
    theta2 = (rvec * rvec).sum(-1)[..., None, None]
    small = theta2 < 1e-6
    safe = torch.where(small, torch.ones_like(theta2), theta2)
    theta = torch.sqrt(safe)
    a = torch.where(small, 0.5 - theta2 / 24.0, (1.0 - torch.cos(theta)) / safe)
    b = torch.where(small, 1.0 / 6.0 - theta2 / 120.0, (theta - torch.sin(theta)) / (safe * theta))
    K = _skew(rvec)
    eye = torch.eye(3, dtype=rvec.dtype, device=rvec.device).expand(K.shape)
    return eye + a * K + b * (K @ K)


def rotated_point_jacobian(rvec: torch.Tensor, p_rot: torch.Tensor, rows: torch.Tensor | None = None) -> torch.Tensor:
    """∂(R(r) X)/∂r = −[R X]× J_l(r): (..., 3) axis-angle vectors and (..., 3) rotated points R X (broadcast)
    -> (..., 3, 3), row i the derivative of coordinate i of R X with respect to r.

    With `rows` (..., m, 3), the derivatives ∂f/∂(R X) of some f, returns the chain rule's (..., m, 3) ∂f/∂r
    = rows · (−[R X]×) · J_l directly: a row a times −[p]× is the cross product p × a."""
    if rows is None:
        return -_skew(p_rot) @ axis_angle_left_jacobian(rvec)
    crossed = torch.linalg.cross(p_rot[..., None, :].expand_as(rows), rows, dim=-1)
    J_l = axis_angle_left_jacobian(rvec)
    lead = crossed.shape[:-3]
    # (J_l's leading dimensions broadcast to `lead`, compared by hand: torch.broadcast_shapes imports sympy on its
    # first call, a cost every calibration command would pay)
    if J_l.dim() == crossed.dim() and J_l.shape[-3] == 1 and crossed.dim() >= 4 and \
            all(j in (1, k) for j, k in zip(J_l.shape[:-3], lead)):
        # one J_l per batch entry of the leading dimensions (a view's pose, all its points): one (N m × 3) @ (3 × 3)
        # product per batch instead of N broadcast 3 × 3 products (rotations with more batch entries than the rows
        # take the broadcast product below)
        n, m = crossed.shape[-3], crossed.shape[-2]
        flat = crossed.reshape((-1, n * m, 3))
        J_flat = J_l.expand(lead + (1, 3, 3)).reshape((-1, 3, 3))
        return torch.bmm(flat, J_flat).reshape(crossed.shape)
    return crossed @ J_l


def matrix_to_axis_angle(R) -> torch.Tensor:
    """(..., 3, 3) rotation matrices -> (..., 3) axis-angle vectors, radians, float64 (via quaternions, kornia;
    not differentiable: for initial values)."""
    from kornia.geometry.conversions import rotation_matrix_to_axis_angle

    R = torch.as_tensor(R, dtype=torch.float64).detach()
    flat = R.reshape(-1, 3, 3)
    out = rotation_matrix_to_axis_angle(flat) if len(flat) else torch.zeros(0, 3, dtype=torch.float64)
    return out.reshape(R.shape[:-2] + (3,))


def euler_xyz_deg(rotation_deg) -> torch.Tensor:
    """Rotation matrix R = Rz · Ry · Rx for angles in degrees about x, then y, then z (float64)."""
    rx, ry, rz = (math.radians(float(a)) for a in rotation_deg)
    cx, sx, cy, sy, cz, sz = math.cos(rx), math.sin(rx), math.cos(ry), math.sin(ry), math.cos(rz), math.sin(rz)
    Rx = torch.tensor([[1, 0, 0], [0, cx, -sx], [0, sx, cx]], dtype=torch.float64)
    Ry = torch.tensor([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]], dtype=torch.float64)
    Rz = torch.tensor([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]], dtype=torch.float64)
    return Rz @ Ry @ Rx


@dataclass(frozen=True)
class CameraTransform:
    """Pose of a camera: x_world = world_from_camera · x_cam + position.

    Attributes:
        world_from_camera: (3, 3) rotation, columns are the camera x, y, z axes in the world.
        position: (3,) camera centre in the world, scene units.
    """

    world_from_camera: torch.Tensor
    position: torch.Tensor

    @staticmethod
    def look_at(position=(0.0, 0.0, 0.0), look_at=(0.0, 0.0, 1.0), up=(0.0, -1.0, 0.0)) -> "CameraTransform":
        return CameraTransform(look_at_rotation(position, look_at, up), torch.as_tensor(position, dtype=torch.float64))

    @staticmethod
    def from_extrinsics(R: torch.Tensor, T: torch.Tensor) -> "CameraTransform":
        """The pose of X_cam = R X_world + T (tiltfit's convention): world_from_camera = Rᵀ, position = −Rᵀ T.

        Args:
            R: (3, 3) rotation camera_from_world; T: (3,) translation, scene units. Tensors keep their graph.
        """
        world_from_camera = R.transpose(-1, -2)
        return CameraTransform(world_from_camera, -(world_from_camera @ T))

    @staticmethod
    def identity() -> "CameraTransform":
        return CameraTransform(torch.eye(3, dtype=torch.float64), torch.zeros(3, dtype=torch.float64))

    def rays_to_world(self, rays_cam: Rays) -> Rays:
        """Move rays built in the camera frame to the world frame (done once per batch)."""
        R = self.world_from_camera.to(rays_cam.origin)
        t = self.position.to(rays_cam.origin)
        return rays_cam.transformed(R, t)

    def points_to_camera(self, p_world: torch.Tensor) -> torch.Tensor:
        """(..., 3) world points to the camera frame."""
        R = self.world_from_camera.to(p_world)
        return (p_world - self.position.to(p_world)) @ R
