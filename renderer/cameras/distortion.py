"""Brown–Conrady lens distortion in OpenCV's order and normalisation, shared by the renderer and tiltfit.

The distortion belongs to the lens: it maps the chief ray's ideal normalised image coordinates
(x, y) = (X/Z, Y/Z) (camera frame, about the principal point) to distorted ones (x_d, y_d):

    r² = x² + y²,  s = (1 + k1 r² + k2 r⁴ + k3 r⁶) / (1 + k4 r² + k5 r⁴ + k6 r⁶)
    x_d = x s + 2 p1 x y + p2 (r² + 2 x²)
    y_d = y s + p1 (r² + 2 y²) + 2 p2 x y

with the coefficients ordered (k1, k2, p1, p2, k3, k4, k5, k6) exactly as `cv2.projectPoints` takes them,
so an untilted camera exported to OpenCV projects identically. Fewer than 8 coefficients mean the missing
ones are 0. The renderer generates rays through `undistort(x_d, y_d)` of each pixel (so CG rendered from a
calibration lines up with the photo); tiltfit's projection applies `distort`.

Scene files: `camera.distortion = {model: "brown_conrady", coefficients: [k1, k2, p1, p2, k3 (, k4, k5, k6)]}`.

About the lens axis (`distort_about_axis`, `undistort_about_axis`): a tilted lens's distortion is symmetric about
its own optical axis, not about the perpendicular from its centre to the sensor. With R = camera_from_lens (the
lens frame's axes in the camera frame, its z the lens axis) the ideal point goes into the lens frame, is
distorted there and comes back along its chief ray:

    q = Rᵀ (x, y, 1),  (x_l, y_l) = D(q_x / q_z, q_y / q_z),  s = R (x_l, y_l, 1),  (x_d, y_d) = (s_x / s_z, s_y / s_z)

R = I is the plain model. This is OpenCV's tilted model (CALIB_TILTED_MODEL) seen from the sensor: OpenCV's
camera frame is our lens frame and its tilt (τx, τy) is R (`renderer.cameras.lens.tilt_rotation`).

Models by name (the terms tiltfit frees; `MODEL_TERMS`): none, k1, k1k2, opencv5 (k1 k2 p1 p2 k3),
rational5 (k1 k2 p1 p2 k4: the rational model with k3 = k5 = k6 = 0, a first-order denominator: opencv5's five
terms with k3 traded for k4; OpenCV's CALIB_RATIONAL_MODEL | CALIB_FIX_K3 | CALIB_FIX_K5 | CALIB_FIX_K6), rational
(all eight). A wide-angle lens's mapping bends over less than its radius squared: one denominator term follows
it where opencv5's polynomial cannot, and unlike the eight terms it is determined by a dozen views (GoPro:
benchmarks/results/rational_terms.md).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from camio.checks import is_finite_number
from renderer.core.params import SceneError

N_COEFFICIENTS = 8
COEFFICIENT_NAMES = ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")
MODEL_TERMS = {
    "none": (),
    "k1": ("k1",),
    "k1k2": ("k1", "k2"),
    "opencv5": ("k1", "k2", "p1", "p2", "k3"),
    "rational5": ("k1", "k2", "p1", "p2", "k4"),
    "rational": COEFFICIENT_NAMES,
}
MODELS = tuple(MODEL_TERMS)
#: A distortion's centre in scene files (`camera.distortion.centre`): the principal point, or a thin lens's own
#: axis (`renderer.Lens.distortion_centre`; the same for an untilted lens and for cameras without a lens).
CENTRES = ("sensor", "lens_axis")


def _padded(coefficients, like: torch.Tensor) -> torch.Tensor:
    """(..., n ≤ 8) coefficients -> (..., 8) on `like`'s device and dtype, zeros appended."""
    k = torch.as_tensor(coefficients, dtype=like.dtype, device=like.device)
    if k.shape[-1] > N_COEFFICIENTS:
        raise ValueError(f"distortion: expected at most {N_COEFFICIENTS} coefficients, got {k.shape[-1]}")
    if k.shape[-1] < N_COEFFICIENTS:
        k = torch.cat([k, k.new_zeros(k.shape[:-1] + (N_COEFFICIENTS - k.shape[-1],))], -1)
    return k


def _radial(r2: torch.Tensor, k: torch.Tensor):
    """Radial factor s(r²) and ds/dr² for (..., 8) coefficients."""
    k1, k2, k3, k4, k5, k6 = (k[..., i] for i in (0, 1, 4, 5, 6, 7))
    a = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    b = 1 + r2 * (k4 + r2 * (k5 + r2 * k6))
    da = k1 + r2 * (2 * k2 + 3 * r2 * k3)
    db = k4 + r2 * (2 * k5 + 3 * r2 * k6)
    return a / b, (da * b - a * db) / (b * b)


def distort(xy: torch.Tensor, coefficients) -> torch.Tensor:
    """Ideal normalised image coordinates -> distorted ones (OpenCV's model; differentiable).

    Args:
        xy: (..., 2) ideal normalised coordinates (X/Z, Y/Z), camera frame, dimensionless.
        coefficients: (≤ 8,) or (..., ≤ 8) (k1, k2, p1, p2, k3, k4, k5, k6), broadcast against xy[..., 0].
    Returns:
        (..., 2) distorted normalised coordinates.
    """
    *_, xd, yd = _distorted(xy, coefficients)
    return torch.stack([xd, yd], -1)


def _distorted(xy: torch.Tensor, coefficients):
    """The terms `distort` and `distort_with_jacobians` share: (x, y, k padded, p1, p2, r², radial factor s, ds/dr²,
    x_d, y_d)."""
    k = _padded(coefficients, xy)
    x, y = xy[..., 0], xy[..., 1]
    p1, p2 = k[..., 2], k[..., 3]
    r2 = x * x + y * y
    s, ds = _radial(r2, k)
    xd = x * s + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * s + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return x, y, k, p1, p2, r2, s, ds, xd, yd


def distort_jacobian(xy: torch.Tensor, coefficients) -> torch.Tensor:
    """(..., 2, 2) Jacobian ∂(x_d, y_d)/∂(x, y) of `distort`."""
    k = _padded(coefficients, xy)
    x, y = xy[..., 0], xy[..., 1]
    p1, p2 = k[..., 2], k[..., 3]
    s, ds = _radial(x * x + y * y, k)
    dxx = s + 2 * x * x * ds + 2 * p1 * y + 6 * p2 * x
    dxy = 2 * x * y * ds + 2 * p1 * x + 2 * p2 * y
    dyy = s + 2 * y * y * ds + 6 * p1 * y + 2 * p2 * x
    return torch.stack([torch.stack([dxx, dxy], -1), torch.stack([dxy, dyy], -1)], -2)


def distort_coefficient_jacobian(xy: torch.Tensor, coefficients, names=COEFFICIENT_NAMES) -> torch.Tensor:
    """(..., 2, n) Jacobian ∂(x_d, y_d)/∂(k1, k2, p1, p2, k3, k4, k5, k6) of `distort` (columns in OpenCV's
    order; the rational terms through s = a / b: ∂s/∂k4 = −s r² / b, and so on); `names` the columns wanted
    (`COEFFICIENT_NAMES`, in any order; default all 8)."""
    k = _padded(coefficients, xy)
    x, y = xy[..., 0], xy[..., 1]
    r2 = x * x + y * y
    s, _ = _radial(r2, k)
    return _coefficient_columns(x, y, r2, s, k, names)


def _coefficient_columns(x, y, r2, s, k, names) -> torch.Tensor:
    """`distort_coefficient_jacobian`'s columns `names` from the shared terms (r², the radial factor s)."""
    k4, k5, k6 = k[..., 5], k[..., 6], k[..., 7]
    b = 1 + r2 * (k4 + r2 * (k5 + r2 * k6))
    r4 = r2 * r2
    powers = {"k1": r2, "k2": r4, "k3": r4 * r2, "k4": r2, "k5": r4, "k6": r4 * r2}
    xy2 = 2 * x * y
    jx, jy = [], []
    for n in names:
        if n == "p1":
            jx.append(xy2)
            jy.append(r2 + 2 * y * y)
        elif n == "p2":
            jx.append(r2 + 2 * x * x)
            jy.append(xy2)
        else:  # ∂s/∂k of a numerator term r^2j / b, of a denominator term −s r^2j / b
            ds = powers[n] / b if n in ("k1", "k2", "k3") else -s * powers[n] / b
            jx.append(x * ds)
            jy.append(y * ds)
    return torch.stack([torch.stack(jx, -1), torch.stack(jy, -1)], -2)


def distort_with_jacobians(xy: torch.Tensor, coefficients, names=COEFFICIENT_NAMES):
    """`distort`, `distort_jacobian` and `distort_coefficient_jacobian` (of the coefficients `names`, or None for
    none) at once, their shared terms (r², the radial factor and its derivative) computed once: the same numbers.

    Returns:
        (x_d (..., 2), ∂x_d/∂xy (..., 2, 2), ∂x_d/∂k (..., 2, len(names)) or None).
    """
    x, y, k, p1, p2, r2, s, ds, xd, yd = _distorted(xy, coefficients)
    dxx = s + 2 * x * x * ds + 2 * p1 * y + 6 * p2 * x
    dxy = 2 * x * y * ds + 2 * p1 * x + 2 * p2 * y
    dyy = s + 2 * y * y * ds + 6 * p1 * y + 2 * p2 * x
    J_xy = torch.stack([torch.stack([dxx, dxy], -1), torch.stack([dxy, dyy], -1)], -2)
    J_k = _coefficient_columns(x, y, r2, s, k, names) if names else None
    return torch.stack([xd, yd], -1), J_xy, J_k


def _solve2(J: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """(..., 2) J⁻¹ b for (..., 2, 2) J by Cramer's rule (batched `torch.linalg.solve` on 2 x 2 systems is
    slow; a singular J gives inf/NaN, which the caller's convergence test rejects)."""
    a, c, d, e = J[..., 0, 0], J[..., 0, 1], J[..., 1, 0], J[..., 1, 1]
    det = a * e - c * d
    return torch.stack([(e * b[..., 0] - c * b[..., 1]) / det, (a * b[..., 1] - d * b[..., 0]) / det], -1)


def undistort(xy_d: torch.Tensor, coefficients, iterations: int = 20, start: torch.Tensor | None = None,
              skip: torch.Tensor | None = None) -> torch.Tensor:
    """Distorted normalised coordinates -> ideal ones: the inverse of `distort`, by Newton's method.

    The iterations run without autograd; one final Newton step with autograd on gives the exact first-order
    derivatives (implicit function theorem) with respect to `xy_d` and the coefficients.

    Args:
        xy_d: (..., 2) distorted normalised coordinates.
        coefficients: as in `distort`.
        iterations: Newton steps (each step is damped to stay where the model is monotonic).
        start: (..., 2) where Newton starts (an interpolated map of the inverse: `UndistortionMap`), NaN where
            there is none [the distorted coordinates themselves]; the root is the same, reached in fewer steps.
        skip: (...,) True where the inverse is known not to exist (returned as NaN without iterating).
    Returns:
        (..., 2) ideal normalised coordinates; NaN where Newton's method did not converge (outside the
        region where the distortion is invertible).
    """
    k = _padded(coefficients, xy_d)
    # Converged means within a few hundred ulps of the input's dtype (1e-9 alone failed 2-8 % of float32 pixels).
    tol = max(1e-9, 256 * torch.finfo(xy_d.dtype).eps)
    with torch.no_grad():
        xy = xy_d.detach().reshape(-1, 2).clone()
        if start is not None:
            s0 = start.detach().reshape(-1, 2).to(xy)
            xy = torch.where(torch.isfinite(s0).all(-1, keepdim=True), s0, xy)
        kd = k.detach()
        target = xy_d.detach().reshape(-1, 2)
        scale = 1 + target.norm(dim=-1)
        # Each point's Newton steps depend on that point alone: the steps run on the points still moving only.
        ulps = 8 * torch.finfo(xy.dtype).eps
        idx = None  # the points still moving (None: all)
        stuck = False  # whether a point that stopped moving is still far from converged
        if skip is not None and bool(skip.any()):
            idx = (~skip.reshape(-1)).nonzero().squeeze(-1)
            stuck = True  # the skipped points are not converged: no early stop on "all converged"
        for _ in range(iterations):
            sub = xy if idx is None else xy[idx]
            tgt = target if idx is None else target[idx]
            err = distort(sub, kd) - tgt
            tiny = err.norm(dim=-1) <= 1e-3 * tol * (scale if idx is None else scale[idx])
            if not stuck and bool(tiny.all()):
                break   # every point converged far below the tolerance: more steps change nothing
            step = _solve2(distort_jacobian(sub, kd), err)
            # Limit steps to half the current radius plus a little: keeps Newton inside the invertible zone.
            limit = 0.5 * sub.norm(dim=-1, keepdim=True) + 0.05
            n = step.norm(dim=-1, keepdim=True)
            new = sub - step * torch.clamp(limit / n.clamp(min=1e-300), max=1.0)
            # A point whose step is a few ulps has converged (some alternate between neighbouring numbers for
            # ever): it leaves the moving set, the result within those ulps of where further steps would go.
            moving = ((new - sub).abs() > ulps * (1 + sub.abs())).any(-1)
            stuck = stuck or bool((~moving & ~tiny).any())
            if idx is None:
                xy = new
                idx = moving.nonzero().squeeze(-1)
            else:
                xy[idx] = new
                idx = idx[moving]
            if idx.numel() == 0:
                break
        xy = xy.reshape(xy_d.shape)
    # The final step's distortion and Jacobian (k has kd's values: the same numbers) also give the checks.
    J = distort_jacobian(xy, k)
    err = distort(xy, k) - xy_d
    with torch.no_grad():
        bad = err.detach().norm(dim=-1) > tol * (1 + xy_d.detach().norm(dim=-1))
        bad |= torch.linalg.det(J.detach()) <= 0
        if skip is not None:
            bad |= skip.reshape(bad.shape)
    out = xy - _solve2(J, err)
    return torch.where(bad[..., None], torch.full_like(out, math.nan), out)


def _pi(v: torch.Tensor) -> torch.Tensor:
    """(..., 3) -> (..., 2) central projection (v_x / v_z, v_y / v_z)."""
    return v[..., :2] / v[..., 2:3]


def _lifted(xy: torch.Tensor) -> torch.Tensor:
    """(..., 2) normalised coordinates -> (..., 3) directions (x, y, 1)."""
    return torch.cat([xy, torch.ones_like(xy[..., :1])], -1)


def _rotated(v: torch.Tensor, R: torch.Tensor) -> torch.Tensor:
    """(..., 3) vectors times (3, 3) R: R v for each."""
    return v @ torch.as_tensor(R).to(v).transpose(-1, -2)


def distort_about_axis(xy: torch.Tensor, coefficients, camera_from_lens) -> torch.Tensor:
    """Ideal normalised camera coordinates -> distorted ones, the distortion applied in the lens's frame (module
    docstring): `distort` of the point's lens-frame coordinates, back along its chief ray.

    Args:
        xy: (..., 2) ideal normalised camera coordinates (X/Z, Y/Z).
        coefficients: as in `distort`.
        camera_from_lens: (3, 3) rotation, its columns the lens frame's axes in the camera frame (a tensor keeps
            its graph), or None for the plain model.
    Returns:
        (..., 2) distorted normalised camera coordinates.
    """
    if camera_from_lens is None:
        return distort(xy, coefficients)
    R = torch.as_tensor(camera_from_lens).to(xy)
    x_l = distort(_pi(_rotated(_lifted(xy), R.transpose(-1, -2))), coefficients)
    return _pi(_rotated(_lifted(x_l), R))


def undistort_about_axis(xy_d: torch.Tensor, coefficients, camera_from_lens, iterations: int = 20,
                         start: torch.Tensor | None = None, skip: torch.Tensor | None = None) -> torch.Tensor:
    """The inverse of `distort_about_axis` (`undistort` in the lens frame); NaN where it does not converge.
    `start`, `skip` as `undistort`'s (`start` in the camera frame's normalised coordinates)."""
    if camera_from_lens is None:
        return undistort(xy_d, coefficients, iterations, start, skip)
    R = torch.as_tensor(camera_from_lens).to(xy_d)
    start_l = None if start is None else _pi(_rotated(_lifted(start.to(xy_d)), R.transpose(-1, -2)))
    x_l = undistort(_pi(_rotated(_lifted(xy_d), R.transpose(-1, -2))), coefficients, iterations, start_l, skip)
    return _pi(_rotated(_lifted(x_l), R))


def _projection_jacobian(v: torch.Tensor) -> torch.Tensor:
    """(..., 2, 3) ∂π(v)/∂v of the central projection π(v) = (v_x / v_z, v_y / v_z)."""
    iz = 1.0 / v[..., 2]
    x, y = v[..., 0] * iz, v[..., 1] * iz
    zero = torch.zeros_like(iz)
    return torch.stack([iz, zero, -x * iz, zero, iz, -y * iz], -1).reshape(v.shape[:-1] + (2, 3))


def distort_about_axis_jacobians(xy: torch.Tensor, coefficients, camera_from_lens, d_camera_from_lens=()):
    """`distort_about_axis` and its derivatives, in closed form (checked against autograd in the tests).

    Args:
        xy, coefficients, camera_from_lens: as in `distort_about_axis` ((3, 3) R, not None).
        d_camera_from_lens: derivatives ∂R/∂a (each (3, 3)) for the angles a the frame depends on.
    Returns:
        (x_d (..., 2), ∂x_d/∂xy (..., 2, 2), ∂x_d/∂coefficients (..., 2, 8), [∂x_d/∂a (..., 2) for each a]).
    """
    R = torch.as_tensor(camera_from_lens).to(xy)
    h = _lifted(xy)
    q = _rotated(h, R.transpose(-1, -2))
    x_n = _pi(q)
    x_l = distort(x_n, coefficients)
    s = _rotated(_lifted(x_l), R)
    J_s = _projection_jacobian(s)                                   # ∂x_d/∂s
    J_l = J_s @ R[:, :2]                                            # ∂x_d/∂x_l
    J_q = distort_jacobian(x_n, coefficients) @ _projection_jacobian(q)  # ∂x_l/∂q
    J_xy = J_l @ J_q @ R.transpose(-1, -2)[:, :2]
    J_k = J_l @ distort_coefficient_jacobian(x_n, coefficients)
    J_a = []
    for dR in d_camera_from_lens:
        dR = torch.as_tensor(dR).to(xy)
        dq = _rotated(h, dR.transpose(-1, -2))
        ds = _rotated(_lifted(x_l), dR) + (J_q @ dq[..., None])[..., 0] @ R[:, :2].transpose(-1, -2)
        J_a.append((J_s @ ds[..., None])[..., 0])
    return _pi(s), J_xy, J_k, J_a


@dataclass(frozen=True)
class BrownConrady:
    """A lens's distortion: coefficients (k1, k2, p1, p2, k3, k4, k5, k6) in OpenCV's order (zeros padded).

    Attributes:
        coefficients: tuple of 8 floats, or a (8,) tensor (a fitted lens's coefficients, e.g. from
            `LensCamera.view_camera`: gradients then reach them through every ray and projection).
        camera_from_lens: None (the distortion about the principal point), or the (3, 3) rotation of a tilted
            lens's frame (`distort_about_axis`; `renderer.Lens.distortion_frame`) [None].
    """

    coefficients: tuple = (0.0,) * N_COEFFICIENTS
    camera_from_lens: object = None

    def __post_init__(self):
        R = self.camera_from_lens
        if R is not None and not isinstance(R, torch.Tensor):  # numbers as a tuple of rows: comparable, hashable
            R = tuple(tuple(float(v) for v in row) for row in R)
            if len(R) != 3 or any(len(row) != 3 for row in R):
                raise ValueError("distortion.camera_from_lens: expected a 3 x 3 rotation")
            object.__setattr__(self, "camera_from_lens", R)
        c = self.coefficients
        if isinstance(c, torch.Tensor):
            if c.dim() != 1 or c.shape[0] > N_COEFFICIENTS:
                raise ValueError(f"distortion.coefficients: expected at most 8 numbers, got shape {tuple(c.shape)}")
            object.__setattr__(self, "coefficients", _padded(c, c))
            return
        c = tuple(float(v) for v in c)
        if len(c) > N_COEFFICIENTS:
            raise ValueError(f"distortion.coefficients: expected at most 8 numbers, got {len(c)}")
        object.__setattr__(self, "coefficients", c + (0.0,) * (N_COEFFICIENTS - len(c)))

    @property
    def is_identity(self) -> bool:
        """All coefficients 0 and none of them a tensor that requires grad (its derivative at 0 is wanted)."""
        c = self.coefficients
        if isinstance(c, torch.Tensor):
            return not c.requires_grad and not bool(c.detach().any())
        return not any(c)

    def distort(self, xy: torch.Tensor) -> torch.Tensor:
        return distort_about_axis(xy, self.coefficients, self.camera_from_lens)

    def undistort(self, xy_d: torch.Tensor, start: torch.Tensor | None = None,
                  skip: torch.Tensor | None = None) -> torch.Tensor:
        return undistort_about_axis(xy_d, self.coefficients, self.camera_from_lens, start=start, skip=skip)

    def to_config(self) -> dict:
        """The scene-file / CALIB.json form (trailing zero rational terms dropped)."""
        c = [float(v) for v in self.coefficients]
        n = N_COEFFICIENTS if any(c[5:]) else 5
        return {"model": "brown_conrady", "coefficients": c[:n]}


def distortion_from_config(path: str, cfg) -> BrownConrady | None:
    """Parse `{model: "brown_conrady", coefficients: [...], centre: "sensor"|"lens_axis"}` (None or null: no
    distortion). The centre is the caller's to apply (`renderer.scene.file`: a thin lens's frame).

    Raises:
        SceneError: naming `path` and the bad field.
    """
    if cfg is None:
        return None
    if not isinstance(cfg, dict):
        raise SceneError(f"{path}: expected an object {{model, coefficients}}, got {cfg!r}")
    for key in cfg:
        if key not in ("model", "coefficients", "centre"):
            raise SceneError(f"{path}.{key}: unknown key (expected one of: centre, coefficients, model)")
    if cfg.get("centre", "sensor") not in CENTRES:
        raise SceneError(f"{path}.centre: expected one of {', '.join(CENTRES)}, got {cfg['centre']!r}")
    model = cfg.get("model", "brown_conrady")
    if model != "brown_conrady":
        raise SceneError(f"{path}.model: expected 'brown_conrady', got {model!r}")
    c = cfg.get("coefficients")
    if not (isinstance(c, list) and 1 <= len(c) <= N_COEFFICIENTS
            and all(is_finite_number(v) for v in c)):
        raise SceneError(f"{path}.coefficients: expected 1 to 8 numbers [k1, k2, p1, p2, k3, k4, k5, k6], "
                         f"got {c!r}")
    return BrownConrady(tuple(c))
