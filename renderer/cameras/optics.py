"""Closed-form optics of a thin lens tilted about the camera x axis (Scheimpflug, hinge rule, blur).

Shared by the `thin_lens` camera (renderer) and the calibration (tiltfit). Pure torch functions: inputs are
tensors or Python numbers that broadcast together; dtype and device follow the tensor inputs (float64 when
all are numbers); everything is differentiable (float64 gradcheck in tests/renderer/test_optics.py).

Conventions (docs/conventions.md). Camera frame x right, y down, z forward; the lens centre O is the origin.
- Sensor plane: z = −w (w: lens centre to sensor, the effective focal length).
- Lens plane: z = y · tan θL (the lens rotated by θL about its centre around the camera x axis);
  lens normal n_L = (0, −sin θL, cos θL).
- Plane of focus Π_F: z = U + y · tan θF, i.e. n_F · p = h with n_F = (0, −sin θF, cos θF) and
  h = U cos θF (the distance of Π_F from O). θL and θF have the same sign.
- Image-plane (screen) coordinates: the upright image of the sensor at distance w in front of the lens,
  (x_s, y_s) = w · (x, y) / z for a point (x, y, z) on its chief ray; the physical sensor point is
  (−x_s, −y_s, −w). Blur ellipses below are given in these coordinates (scene units, mm in tiltfit);
  divide by the pixel pitch for pixels.
Lengths in one unit (scene units; mm in tiltfit); angles in radians.

Exact relations for an ideal thin lens of focal length f (the physics notes of the papers' NOTES.md):
- Scheimpflug: sensor plane, lens plane and Π_F meet in one line, at z = −w, y = −w / tan θL, so
      tan θF = (U + w) tan θL / w.
- Hinge rule: Π_F, the lens's front focal plane (n_L · p = f) and the plane z = 0 meet in one line, at
  z = 0, y = −f / sin θL, so U / tan θF = f / sin θL, equivalently
      U = f w / (w cos θL − f)        (the object conjugate of the sensor centre along the axis).
- Both together: tan θF = w sin θL / (w cos θL − f), i.e. sin(θF − θL) = (f / w) sin θF.
The paper's eq. (1), θL = atan(f tan θF / (U + f)), has f where the Scheimpflug relation has w: for
w = 55.39, U = 618.4 (f = 50.84) a 5° lens tilt gives U = 648.4 (hinge rule) and θF = 48.03°, which (1)
maps back to θL = 4.62°.

Blur. The spot of a point X is the aperture disc (diameter d, in the tilted lens plane) projected from X
onto Π_F and then through O onto the image plane; for a tilted lens it is an ellipse (`blur_ellipse`).
Three closed forms, from crude to exact:
- `blur_diameter_paper`: the paper's eq. (4) (eq. (2) when θF = 0), b = w d |1/(U + y tan θF) − 1/z|.
- `blur_diameter_first_order`: b = w d |1/z_f − 1/z| with z_f = U w / (w − y_s tan θF) the depth where
  X's chief ray meets Π_F. Equivalently b = w d · dist(X, Π_F) / (h · z). This is the exact spot width
  along x to first order in d, and finite for every pixel (1/z_f ≤ 0 where the chief ray never meets Π_F
  in front of the lens). It differs from the paper's (4) by the factor (U + y tan θF) / U: the paper
  divides by the focus depth at X's own height instead of by U.
- `blur_ellipse` / `blur_width` / `blur_diameter_exact`: the exact ellipse (centre and shape matrix), its
  width along any image direction, and its equivalent-area diameter. Along y (the tilt direction) the
  width is, to first order in d, the first-order value times cos θL − (y / z) sin θL (the tilted aperture
  seen from X, foreshortened).
The exact ellipse is the support of the spot; a rendered spot's intensity is not exactly uniform over it
(the projection from the lens disc is projective, not affine), which matters little for d ≪ z.
"""
from __future__ import annotations

import torch

#: Names of the blur closed forms `blur_diameter` dispatches to (the calibration model's `blur_model`).
BLUR_MODELS = ("ellipse", "first_order", "paper")

__all__ = [
    "BLUR_JACOBIAN_ARGS", "BLUR_MODELS", "blur_diameter", "blur_diameter_exact", "blur_diameter_jacobian",
    "blur_diameter_first_order", "blur_diameter_paper",
    "blur_ellipse", "blur_width",
    "focal_length", "focus_depth", "focus_distance_tilted", "hinge_line_y", "scheimpflug_line_y",
    "theta_F_from_theta_L", "theta_F_from_theta_L_f", "theta_L_from_theta_F", "theta_L_from_theta_F_f",
    "theta_L_paper",
]


def _tensors(*xs):
    """Convert numbers and tensors to tensors of one floating dtype and device (float64 for numbers)."""
    ts = [x for x in xs if isinstance(x, torch.Tensor)]
    dtype = torch.float64
    if ts:
        floats = [t.dtype for t in ts if t.is_floating_point()]
        dtype = floats[0] if floats else torch.float64
        for d in floats[1:]:
            dtype = torch.promote_types(dtype, d)
    device = ts[0].device if ts else None
    return [torch.as_tensor(x, dtype=dtype, device=device) for x in xs]


# --- Scheimpflug and hinge relations -------------------------------------------------------------------

def theta_F_from_theta_L(theta_L, w, U) -> torch.Tensor:
    """Plane-of-focus tilt from the lens tilt, given w and U (Scheimpflug line), exact.

    tan θF = (U + w) tan θL / w.

    Args:
        theta_L: lens tilt about the camera x axis, radians.
        w: lens centre to sensor, length; U: lens centre to the plane of focus along the axis, length.
    Returns:
        θF, radians, |θF| < π/2, same sign as θL.
    """
    theta_L, w, U = _tensors(theta_L, w, U)
    return torch.atan((U + w) * torch.tan(theta_L) / w)


def theta_L_from_theta_F(theta_F, w, U) -> torch.Tensor:
    """Lens tilt from the plane-of-focus tilt, given w and U; the exact inverse of `theta_F_from_theta_L`.

    tan θL = w tan θF / (U + w). Radians in and out; w, U lengths.
    """
    theta_F, w, U = _tensors(theta_F, w, U)
    return torch.atan(w * torch.tan(theta_F) / (U + w))


def theta_F_from_theta_L_f(theta_L, w, f) -> torch.Tensor:
    """Plane-of-focus tilt of a lens of focal length f tilted by θL with the sensor at w (Scheimpflug + hinge).

    tan θF = w sin θL / (w cos θL − f). Radians; w, f lengths (w cos θL > f for a real plane of focus).
    """
    theta_L, w, f = _tensors(theta_L, w, f)
    return torch.atan2(w * torch.sin(theta_L), w * torch.cos(theta_L) - f)


def theta_L_from_theta_F_f(theta_F, w, f) -> torch.Tensor:
    """Lens tilt that puts the plane of focus at tilt θF for focal length f and sensor distance w.

    θL = θF − asin((f / w) sin θF), the inverse of `theta_F_from_theta_L_f`. Radians; w > f lengths.
    """
    theta_F, w, f = _tensors(theta_F, w, f)
    return theta_F - torch.asin(f / w * torch.sin(theta_F))


def focus_distance_tilted(w, f, theta_L=0.0) -> torch.Tensor:
    """U, the on-axis distance of the plane of focus, for a lens of focal length f tilted by θL (hinge rule).

    U = f w / (w cos θL − f); θL = 0 gives the thin-lens equation 1/f = 1/w + 1/U. Lengths; θL radians.
    Tilting a lens focused at U0 about its centre (sensor fixed) moves U: 618.4 → 648.4 mm for w = 55.39,
    θL = 5°.
    """
    w, f, theta_L = _tensors(w, f, theta_L)
    return f * w / (w * torch.cos(theta_L) - f)


def focal_length(w, U, theta_L=0.0) -> torch.Tensor:
    """Focal length of the thin lens whose sensor at w is conjugate to the plane of focus at U, lens tilt θL.

    f = U w cos θL / (U + w) (the inverse of `focus_distance_tilted`); untilted 1/f = 1/w + 1/U.
    """
    w, U, theta_L = _tensors(w, U, theta_L)
    return U * w * torch.cos(theta_L) / (U + w)


def theta_L_paper(theta_F, f, U) -> torch.Tensor:
    """The paper's eq. (1), θL = atan(f tan θF / (U + f)), for comparison only (see module docstring).

    The exact relation has w in place of f (`theta_L_from_theta_F`); with f < w eq. (1) underestimates |θL|.
    """
    theta_F, f, U = _tensors(theta_F, f, U)
    return torch.atan(f * torch.tan(theta_F) / (U + f))


def scheimpflug_line_y(w, theta_L) -> torch.Tensor:
    """y of the Scheimpflug line (sensor plane ∩ lens plane ∩ plane of focus), which lies at z = −w.

    y = −w / tan θL (±inf for θL = 0: the planes are parallel). The line runs along the camera x axis.
    """
    w, theta_L = _tensors(w, theta_L)
    return -w / torch.tan(theta_L)


def hinge_line_y(f, theta_L) -> torch.Tensor:
    """y of the hinge line (plane of focus ∩ front focal plane ∩ plane z = 0), which lies at z = 0.

    y = −f / sin θL; parallel to the camera x axis.
    """
    f, theta_L = _tensors(f, theta_L)
    return -f / torch.sin(theta_L)


def focus_depth(y, U, theta_F=0.0) -> torch.Tensor:
    """Depth z = U + y tan θF of the plane of focus at camera-frame height y (lengths; θF radians)."""
    y, U, theta_F = _tensors(y, U, theta_F)
    return U + y * torch.tan(theta_F)


# --- Blur ----------------------------------------------------------------------------------------------

def blur_diameter_paper(y, z, w, U, d, theta_F=0.0) -> torch.Tensor:
    """The paper's blur diameter on the sensor, eq. (4): b = w d |1/(U + y tan θF) − 1/z| (eq. (2) at θF = 0).

    Args:
        y, z: the point's camera-frame height and depth, lengths.
        w, U, d: sensor distance, on-axis focus distance, aperture diameter, lengths; θF radians.
    Returns:
        b, length on the sensor (same unit as w). Exact for θF = 0; see the module docstring otherwise.
    """
    y, z, w, U, d, theta_F = _tensors(y, z, w, U, d, theta_F)
    return w * d * torch.abs(1.0 / (U + y * torch.tan(theta_F)) - 1.0 / z)


def blur_diameter_first_order(p_cam, w, U, d, theta_F=0.0) -> torch.Tensor:
    """Blur diameter to first order in d: b = w d |1/z_f − 1/z|, z_f the depth where the chief ray meets Π_F.

    1/z_f = (1 − (y/z) tan θF) / U, so b = w d |U + y tan θF − z| / (U z) = w d · dist(X, Π_F) / (h z).
    Exact for θF = 0 (eq. (2)); for a tilt it is the spot's width along x to first order in d (along y
    multiply by cos θL − (y/z) sin θL). Finite for points whose chief ray has no finite focus distance.

    Args:
        p_cam: (..., 3) points in the camera frame (z > 0), lengths.
        w, U, d: lengths; theta_F: radians (broadcast against p_cam[..., 0]).
    Returns:
        (...,) diameter on the sensor, same length unit.
    """
    p_cam, w, U, d, theta_F = _tensors(p_cam, w, U, d, theta_F)
    y, z = p_cam[..., 1], p_cam[..., 2]
    return w * d * torch.abs(U + y * torch.tan(theta_F) - z) / (U * z)


def _ellipse_terms(p_cam, w, U, d, theta_F):
    """Pieces of the blur ellipse (see `blur_ellipse`): A = s (e_x e_xᵀ + α g gᵀ); returns sqrt(s), not s."""
    p_cam, w, U, d, theta_F = _tensors(p_cam, w, U, d, theta_F)
    x, y, z = p_cam.unbind(-1)
    theta_L = theta_L_from_theta_F(theta_F, w, U)
    sF, cF = torch.sin(theta_F), torch.cos(theta_F)
    sL, cL = torch.sin(theta_L), torch.cos(theta_L)
    r = d / 2
    h = U * cF
    k = h - (cF * z - sF * y)
    gx, gy = torch.broadcast_tensors(-x * sL / z, cL - y * sL / z)
    m = z * torch.sin(theta_L - theta_F) + k * sL
    hz2 = (h * z) ** 2
    delta = hz2 - (r * m) ** 2
    bounded = delta > 0
    delta = torch.where(bounded, delta, torch.ones_like(delta))
    # sqrt(s) = |r w k| / sqrt(Δ) is kept separately so widths have finite gradients for points in focus.
    sqrt_s = torch.abs(r * w * k) / torch.sqrt(delta)
    alpha = hz2 / delta
    cx = w * x / z - r**2 * w * k * m / delta * gx
    cy = w * y / z - r**2 * w * k * m / delta * gy
    return sqrt_s, alpha, gx, gy, torch.stack(torch.broadcast_tensors(cx, cy), -1), bounded


def blur_ellipse(p_cam, w, U, d, theta_F=0.0) -> tuple[torch.Tensor, torch.Tensor]:
    """Exact blur spot of a point for the tilted thin lens: an ellipse on the image plane.

    The lens tilt is θL = atan(w tan θF / (U + w)) (exact Scheimpflug). The aperture disc, radius r = d/2
    in the lens plane, is mapped onto the image plane by the homography lens point S -> Π_F ∩ line(X, S) ->
    central projection through O; the image of its boundary is the ellipse
        {q : (q − c)ᵀ A⁻¹ (q − c) ≤ 1}.
    In closed form, with k = h − n_F·X (signed distance of X from Π_F), g = (−x sin θL / z,
    cos θL − y sin θL / z), m = z sin(θL − θF) + k sin θL and Δ = (h z)² − r² m²:
        A = (r w k)² / Δ · (e_x e_xᵀ + (h z)² / Δ · g gᵀ),   c = w (x, y) / z − r² w k m g / Δ.
    For θF = 0 this is the circle of radius w r |1/U − 1/z| about the pinhole image (eq. (2)). Δ ≤ 0 means
    the spot is unbounded (X so close to the lens that Π_F is seen edge-on through the aperture); A is +inf
    there.

    Args:
        p_cam: (..., 3) point in the camera frame, lengths.
        w, U, d: lengths; theta_F: radians; broadcast against p_cam[..., 0].
    Returns:
        center: (..., 2) ellipse centre, image-plane coordinates (x_s, y_s) at distance w, lengths.
        shape: (..., 2, 2) symmetric matrix A (lengths²); the half-width along a unit direction n is
            sqrt(nᵀ A n), and a uniform spot over the ellipse has covariance A / 4.
    """
    sqrt_s, alpha, gx, gy, center, bounded = _ellipse_terms(p_cam, w, U, d, theta_F)
    s = sqrt_s**2
    axx = s * (1 + alpha * gx * gx)
    axy = s * alpha * gx * gy
    ayy = s * alpha * gy * gy
    shape = torch.stack([torch.stack([axx, axy], -1), torch.stack([axy, ayy], -1)], -2)
    shape = torch.where(bounded[..., None, None], shape, torch.full_like(shape, float("inf")))
    return center, shape


def blur_width(p_cam, w, U, d, theta_F, direction) -> torch.Tensor:
    """Exact width of the blur spot along a unit image-plane direction (the extent across an edge).

    width = 2 sqrt(nᵀ A n) with A from `blur_ellipse`. Across a horizontal edge (n = (0, 1)) this is the
    width along the tilt direction.

    Args:
        p_cam: (..., 3) camera-frame point; w, U, d lengths; theta_F radians.
        direction: (..., 2) unit vector n in image-plane coordinates (x right, y down).
    Returns:
        (...,) width, lengths on the sensor (+inf where the spot is unbounded).
    """
    sqrt_s, alpha, gx, gy, _, bounded = _ellipse_terms(p_cam, w, U, d, theta_F)
    n = _tensors(direction, sqrt_s)[0]
    ng = n[..., 0] * gx + n[..., 1] * gy
    width = 2 * sqrt_s * torch.sqrt(n[..., 0] ** 2 + alpha * ng * ng)
    return torch.where(bounded, width, torch.full_like(width, float("inf")))


def blur_diameter_exact(p_cam, w, U, d, theta_F=0.0) -> torch.Tensor:
    """Equivalent-area diameter of the exact blur ellipse: 2 (det A)^(1/4) = 2 sqrt(a b), a, b the semi-axes.

    det A = s² α g_y² in the notation of `blur_ellipse`. Equals eq. (2) for θF = 0. Args as `blur_ellipse`;
    returns (...,) lengths on the sensor (+inf where the spot is unbounded). Its gradient is finite for
    points on the plane of focus (the subgradient of |k| at 0), as is `blur_width`'s.
    """
    sqrt_s, alpha, gx, gy, _, bounded = _ellipse_terms(p_cam, w, U, d, theta_F)
    dia = 2 * sqrt_s * torch.sqrt(torch.sqrt(alpha) * torch.abs(gy))
    return torch.where(bounded, dia, torch.full_like(dia, float("inf")))


def blur_diameter(p_cam, w, U, d, theta_F=0.0, blur_model: str = "ellipse") -> torch.Tensor:
    """Blur diameter on the sensor for camera-frame points by the named closed form (all equal eq (2) at θF = 0).

    Args:
        p_cam: (..., 3) camera-frame points. Lens parameters: numbers or broadcastable tensors (lengths, rad).
        blur_model: "ellipse" (`blur_diameter_exact`, the equivalent-area diameter of the exact spot),
            "first_order" (`blur_diameter_first_order`) or "paper" (`blur_diameter_paper`, eq (4)).
    Returns:
        (...,) diameter on the sensor, in the unit of the lengths.
    """
    if blur_model == "ellipse":
        return blur_diameter_exact(p_cam, w, U, d, theta_F)
    if blur_model == "first_order":
        return blur_diameter_first_order(p_cam, w, U, d, theta_F)
    if blur_model == "paper":
        return blur_diameter_paper(p_cam[..., 1], p_cam[..., 2], w, U, d, theta_F)
    raise ValueError(f"blur_model: expected one of {BLUR_MODELS}, got {blur_model!r}")


# --- Jacobians of the blur closed forms ----------------------------------------------------------------

#: Order of the columns of `blur_diameter_jacobian`: the point (camera frame) and the lens.
BLUR_JACOBIAN_ARGS = ("x", "y", "z", "w", "U", "d", "theta_F")


def _unit_derivatives(like: torch.Tensor):
    """d(x), d(y), …, d(θF) as (…, 7) rows of the identity, broadcastable against `like`."""
    eye = torch.eye(7, dtype=like.dtype, device=like.device)
    return [eye[i] for i in range(7)]


def blur_diameter_jacobian(p_cam, w, U, d, theta_F=0.0, blur_model: str = "ellipse"):
    """The blur diameter (`blur_diameter`) and its derivatives with respect to the point and the lens, in closed
    form (the chain rule written out, no autodiff; checked against autograd in tests/renderer/test_jacobians.py).

    Args:
        p_cam: (..., 3) camera-frame points, lengths; w, U, d lengths and theta_F radians, numbers or 0-dim
            tensors (one lens); blur_model as in `blur_diameter`.
    Returns:
        b: (...,) diameter on the sensor (as `blur_diameter`);
        J: (..., 7) ∂b/∂(x, y, z, w, U, d, θF) (`BLUR_JACOBIAN_ARGS`). Where |·| has a kink (a point on the
        plane of focus) the derivative takes sign 0, as autograd does; where the spot is unbounded (b = inf)
        J is NaN.
    """
    p_cam, w, U, d, theta_F = _tensors(p_cam, w, U, d, theta_F)
    x, y, z = p_cam.unbind(-1)
    dx, dy, dz, dw, dU, dd, dth = _unit_derivatives(p_cam)
    x, y, z = x[..., None], y[..., None], z[..., None]  # trailing axis broadcasts against the 7 derivatives
    tF = torch.tan(theta_F)
    dtF = (1.0 + tF * tF) * dth
    if blur_model == "paper":
        zf = U + y * tF                                     # focus depth at the point's height
        a = 1.0 / zf - 1.0 / z
        s = torch.sign(a)
        da = -(dU + tF * dy + y * dtF) / (zf * zf) + dz / (z * z)
        b = w * d * a.abs()
        J = d * a.abs() * dw + w * a.abs() * dd + w * d * s * da
        return b[..., 0], J
    if blur_model == "first_order":
        n = U + y * tF - z
        s = torch.sign(n)
        uz = U * z
        dn = dU + tF * dy + y * dtF - dz
        duz = z * dU + U * dz
        q = n.abs() / uz
        dq = s * dn / uz - n.abs() * duz / (uz * uz)
        return (w * d * q)[..., 0], d * q * dw + w * q * dd + w * d * dq
    if blur_model != "ellipse":
        raise ValueError(f"blur_model: expected one of {BLUR_MODELS}, got {blur_model!r}")
    # θL = atan(w tan θF / (U + w)) (exact Scheimpflug)
    tL = w * tF / (U + w)
    dtL = (tF * dw + w * dtF) / (U + w) - w * tF * (dU + dw) / (U + w) ** 2
    theta_L = torch.atan(tL)
    dthL = dtL / (1.0 + tL * tL)
    sF, cF = torch.sin(theta_F), torch.cos(theta_F)
    sL, cL = torch.sin(theta_L), torch.cos(theta_L)
    dsF, dcF = cF * dth, -sF * dth
    dsL, dcL = cL * dthL, -sL * dthL
    r, dr = d / 2, dd / 2
    h = U * cF
    dh = cF * dU + U * dcF
    k = h - (cF * z - sF * y)
    dk = dh - (z * dcF + cF * dz - y * dsF - sF * dy)
    gy = cL - y * sL / z
    dgy = dcL - (sL * dy + y * dsL) / z + y * sL * dz / (z * z)
    sLF = torch.sin(theta_L - theta_F)
    m = z * sLF + k * sL
    dm = sLF * dz + z * torch.cos(theta_L - theta_F) * (dthL - dth) + sL * dk + k * dsL
    hz = h * z
    dhz = z * dh + h * dz
    delta = hz * hz - (r * m) ** 2
    ddelta = 2 * hz * dhz - 2 * r * m * m * dr - 2 * r * r * m * dm
    bounded = delta > 0
    delta = torch.where(bounded, delta, torch.ones_like(delta))
    # b = 2 |q| E with q = r w k and E = sqrt(|h z| |g_y|) Δ^(−3/4) (`blur_diameter_exact`)
    q = r * w * k
    dq = w * k * dr + r * k * dw + r * w * dk
    E = torch.sqrt(hz.abs() * gy.abs()) * delta ** -0.75
    dE = E * (0.5 * torch.sign(hz) * dhz / hz.abs() + 0.5 * torch.sign(gy) * dgy / gy.abs() - 0.75 * ddelta / delta)
    b = 2 * q.abs() * E
    J = 2 * torch.sign(q) * E * dq + 2 * q.abs() * dE
    b = torch.where(bounded, b, torch.full_like(b, float("inf")))
    J = torch.where(bounded, J, torch.full_like(J, float("nan")))
    return b[..., 0], J
