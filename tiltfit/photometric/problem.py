"""The photometric least-squares problem: each fitted pixel's residual (photo − rendered board under the
exposure) and its Jacobian with respect to the lens, the poses and the exposure (`_Problem.evaluate`). The
lens block holds the camera's stored lens parameters the fit moves, in the order of `LENS_PARAMETERS`, the lens
vector of `renderer.cameras.lens_vector` (which decodes it: `lens_values`).
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass

import torch

from renderer.cameras import LENS_PARAMETERS, concentric_disk, lens_values

from tiltfit.photometric.aperture import checker_dark_fraction_disc
from tiltfit.calibrate.model import LensCamera
from tiltfit.target.layout import Target
from .render import SUBPIXELS, SUBPIXELS_SHARP, dark_fraction_lens_samples, sample_points, sub_points


#: Pixels per block of the Jacobian (bounds its memory; results do not depend on it).
JACOBIAN_BLOCK = 2048

#: Pixels between the image centre and the other two points the focus geometry of an undistorted camera is taken
#: at (`_Problem._focus`); any span gives the same focus points to rounding.
FOCUS_BASIS_SPAN = 256.0


@dataclass
class _View:
    uv: torch.Tensor          # (N, 2) pixels used
    observed: torch.Tensor    # (N,) linear intensities
    n_closed_form: int        # the first n_closed_form pixels integrate the aperture in closed form
    rho2: torch.Tensor        # (N,) squared distance from the image centre, 1 at the corners
    xy: torch.Tensor | None = None   # (N, 2) pixel coordinates about the image centre, ±1 at the edges
    n_sharp: int = 0          # the first n_sharp of them with SUBPIXELS_SHARP points a side (blur < SHARP_BLUR_PX)


class _ViewGeometry(torch.nn.Module):
    """The camera under `torch.func.functional_call`: `fn(camera.view_camera(view))` with substituted tensors."""

    def __init__(self, camera: LensCamera):
        super().__init__()
        self.camera = camera

    def forward(self, view: int, fn):
        return fn(self.camera.view_camera(view))


class _Problem:
    """The photometric least-squares problem: pixels of every view, the camera they are rendered with, and
    `evaluate` in the solver's form (residuals in units of `scale`, Jacobians by block)."""

    def __init__(self, camera: LensCamera, target: Target, data: list, lens_uv: torch.Tensor, say=None):
        self.camera, self.target, self.data, self.lens_uv = camera, target, data, lens_uv
        self.lens_xy = concentric_disk(lens_uv.to(torch.float64))   # the samples' points of the unit disc
        self.geometry = _ViewGeometry(camera)
        self.n_edges = max(len(target.x_edges), len(target.y_edges))
        # Every cell edge that cuts a disc gets its two-line term (`checker_dark_fraction_disc` integrates only the
        # pairs that cut, so all cost no more than a few).
        self.near = self.n_edges
        self.scale = 1.0
        self.psf_fixed = 0.0
        self.say, self.t0, self.n_jacobians = say, time.perf_counter(), 0
        self.lens_start = torch.stack([getattr(camera, n).detach() for n in LENS_PARAMETERS]).to(torch.float64)
        self.free = list(range(4))                     # the stored lens parameters the fit moves
        self.bound = torch.full((4,), math.inf, dtype=torch.float64)

    # --- the lens block: the free stored parameters, each within ±bound of the start (smoothly, by tanh) -----
    def full_lens(self, z: torch.Tensor) -> torch.Tensor:
        """(4,) stored lens parameters of the solver's lens block z (len(free),): start + b tanh(z / b)."""
        lens = self.lens_start.clone()
        if self.free:
            b = self.bound[self.free]
            step = torch.where(torch.isfinite(b), b * torch.tanh(z / b.clamp(max=1e300)), z)
            lens[self.free] = self.lens_start[self.free] + step
        return lens

    def lens_jacobian(self, z: torch.Tensor) -> torch.Tensor:
        """(4, len(free)) d full_lens / dz."""
        J = torch.zeros(4, len(self.free), dtype=torch.float64)
        if self.free:
            b = self.bound[self.free]
            d = torch.where(torch.isfinite(b), 1.0 / torch.cosh(z / b.clamp(max=1e300)) ** 2, torch.ones_like(z))
            J[self.free, torch.arange(len(self.free))] = d
        return J

    # --- the camera of a state -----------------------------------------------------------------------------
    def _params(self, v: int, lens: torch.Tensor, pose: torch.Tensor) -> dict:
        rv, Ts = self.camera.rvec.detach(), self.camera.T_scaled.detach()
        out = {f"camera.{n}": lens[i] for i, n in enumerate(LENS_PARAMETERS)}
        out["camera.rvec"] = torch.cat([rv[:v], pose[None, :3], rv[v + 1:]])
        out["camera.T_scaled"] = torch.cat([Ts[:v], pose[None, 3:6], Ts[v + 1:]])
        return out

    def _call(self, v: int, geo: torch.Tensor, fn):
        """fn(view camera of view v) with lens = geo[:4], pose = geo[4:10]."""
        return torch.func.functional_call(self.geometry, self._params(v, geo[:4], geo[4:10]), (v, fn))

    # --- dark fractions and their Jacobians ------------------------------------------------------------------
    def _focus(self, v: int, geo: torch.Tensor, jacobian: bool):
        """View v's focus geometry at the state `geo`, as a function of sensor points: at(pts (N, S, 2)) ->
        (q_h (N, S, 4), centre (3,), axes (2, 3), chain), where chain(gq (N, S, 4), gc (N, 3), ga (N, 2, 3)) ->
        (N, 10) turns a function's gradients with respect to them (per pixel) into its derivatives by (lens, pose);
        chain is None without `jacobian`.

        The focus point is affine in the ideal (distortion-free) sensor point (`ThinLensCamera.focus_geometry`:
        the screen point, its focus weight and the pose's map are all affine), so it and its derivative are taken
        once a view and state at three ideal points of the image (`_basis`) and combined for every point (equal to
        rounding, 1e-13 relative). With distortion a point's ideal position is its Newton root (`undistort_pixels`,
        once, without derivatives), and its derivative by (lens, pose) the implicit function's, through one Newton
        step in forward mode (`Camera.undistort_pixels_from`; distortion and principal point are held, but the
        focal length moves the normalised coordinates, and `sigma._held_covariance` moves k1 between calls).

        The three points' 21 numbers are differentiated in reverse mode (`jacrev`, one batched backward pass): under
        forward mode each of the camera's operations with a Python number (`x * 2`, `1 - x`) runs through torch's
        Python reference implementation (docs/history.md, 2026-11-29). The ideal points have as many outputs as
        points: forward mode's 10 tangents stay cheaper there."""
        def focus(g):
            out = self._call(v, g, lambda cam: cam.focus_geometry(self._basis(geo.dtype), distorted=False)[:3])
            return out, tuple(o.detach() for o in out)

        if jacobian:
            d, (q, c, a) = torch.func.jacrev(focus, has_aux=True)(geo)
        else:
            d = None
            with torch.no_grad():
                q, c, a = focus(geo)[1]
        q0, qu, qv = q[0], q[1] - q[0], q[2] - q[0]
        distorted = bool((self.camera.distortion.detach() != 0).any())
        d_intrinsics = None
        if distorted and jacobian and self.camera.distortion_centre != "lens_axis":
            def intrinsics(g):   # (f_x, f_y, c_x, c_y) px
                out = self._call(v, g, lambda cam: torch.stack(
                    [torch.as_tensor(t).to(geo) for t in (*cam.focal_px, *cam.screen.center_px)]))
                return out, out.detach()

            d_intrinsics = torch.func.jacrev(intrinsics, has_aux=True)(geo)[0]   # (4, 10)

        def at(pts):
            ideal_px, d_ideal = self._ideal(v, geo, pts, distorted, jacobian, d_intrinsics)
            su, sv = self._basis_coordinates(ideal_px)
            q_pts = q0 + su[..., None] * qu + sv[..., None] * qv
            if d is None:
                return q_pts, c, a, None
            dq, dc, da = d
            d0, du, dv = dq[0], dq[1] - dq[0], dq[2] - dq[0]

            def chain(gq, gc, ga):
                out = (gq.sum(1) @ d0 + (gq * su[..., None]).sum(1) @ du + (gq * sv[..., None]).sum(1) @ dv
                       + gc @ dc + torch.einsum("nij,ijp->np", ga, da))
                if d_ideal is not None:   # the ideal points move with the focal length: q moves along qu, qv
                    g_ideal = torch.stack([(gq * qu).sum(-1), (gq * qv).sum(-1)], -1) / FOCUS_BASIS_SPAN
                    out = out + torch.einsum("nsk,nskp->np", g_ideal, d_ideal)
                return out

            return q_pts, c, a, chain
        return at

    def _ideal(self, v: int, geo: torch.Tensor, pts: torch.Tensor, distorted: bool, jacobian: bool,
               d_intrinsics: torch.Tensor | None):
        """(ideal points (N, S, 2) of view v's sensor points `pts` at the state `geo`, their derivatives by (lens,
        pose) (N, S, 2, 10) or None without `jacobian`), for `_focus`. `d_intrinsics`: (4, 10) derivatives of
        (f_x, f_y, c_x, c_y) by (lens, pose), for a distortion about the principal point."""
        if not distorted:
            return pts, None
        with torch.no_grad():
            # A pixel's points lie within it: Newton starts each from its pixel centre's root, moved by its
            # offset (two or three steps instead of up to 20 from the distorted point; the same root).
            centre = pts.mean(-2, keepdim=True)
            start = self._call(v, geo, lambda cam: cam.undistort_pixels(centre))[0] + (pts - centre)
            ideal_px, valid = self._call(v, geo, lambda cam: cam.undistort_pixels(pts, start))
        if not jacobian:
            return ideal_px, None
        if self.camera.distortion_centre == "lens_axis":   # the lens frame moves with θF: forward mode
            def step(g):
                out = self._call(v, g, lambda cam: cam.undistort_pixels_from(pts, ideal_px, valid))
                return out, out.detach()

            d_ideal, ideal_px = torch.func.jacfwd(step, has_aux=True)(geo)
            return ideal_px, d_ideal
        with torch.no_grad():   # about the principal point: only the intrinsics move the ideal points
            d_ideal = self._call(v, geo, lambda cam: cam.undistort_pixels_jacobian(pts, ideal_px, valid))
        return ideal_px, d_ideal @ d_intrinsics

    def _basis(self, dtype) -> torch.Tensor:
        """(3, 2) the image centre and the points FOCUS_BASIS_SPAN px to its right and below it."""
        cu, cv = self.camera.image_size_px[0] / 2.0, self.camera.image_size_px[1] / 2.0
        return torch.tensor([[cu, cv], [cu + FOCUS_BASIS_SPAN, cv], [cu, cv + FOCUS_BASIS_SPAN]], dtype=dtype)

    def _basis_coordinates(self, pts: torch.Tensor):
        """(su, sv) (N, S): `pts` in the basis of `_basis` (its origin, FOCUS_BASIS_SPAN px a unit)."""
        cu, cv = self.camera.image_size_px[0] / 2.0, self.camera.image_size_px[1] / 2.0
        return (pts[..., 0] - cu) / FOCUS_BASIS_SPAN, (pts[..., 1] - cv) / FOCUS_BASIS_SPAN

    def _closed(self, focus, uv: torch.Tensor, jacobian: bool, subpixels: int = SUBPIXELS):
        """(N,) dark fractions in closed form and (N, 10) their derivatives by (lens, pose): forward mode through
        the focus geometry (`_focus`), one reverse pass through the aperture integral (elementwise in the
        points), chained."""
        pts = sub_points(uv, subpixels)
        q, c, a, chain = focus(pts)
        if not jacobian:
            with torch.no_grad():
                return checker_dark_fraction_disc(q, c, a, self.target, self.near).mean(-1), None
        n, s = pts.shape[:2]
        with torch.enable_grad():
            # Each pixel's own copy of the lens centre and axes (broadcast over its points): the gradient of the
            # sum is every pixel's partials.
            qq = q.clone().requires_grad_()
            cc = c.expand(n, 1, 3).clone().requires_grad_()
            aa = a.expand(n, 1, 2, 3).clone().requires_grad_()
            dark = checker_dark_fraction_disc(qq, cc, aa, self.target, self.near)
            grads = torch.autograd.grad(dark.sum(), (qq, cc, aa), allow_unused=True)
        gq, gc, ga = (torch.zeros_like(t) if g is None else g for g, t in zip(grads, (qq, cc, aa)))
        return dark.detach().mean(-1), chain(gq, gc.reshape(n, 3), ga.reshape(n, 2, 3)) / s

    def _samples(self, focus, psf: torch.Tensor, uv: torch.Tensor, jacobian: bool):
        """(N,) dark fractions by the fixed lens samples and (N, 11) their derivatives by (lens, pose, psf): as
        `_closed`, forward mode through the 7 focus points a pixel (`render.sample_points`) and one reverse pass
        through the samples' checker (elementwise in the pixels), chained."""
        pts = sample_points(uv)
        q, c, a, chain = focus(pts)
        if not jacobian:
            with torch.no_grad():
                return dark_fraction_lens_samples(self.target, q, c, a, self.lens_xy, psf * psf), None
        n = pts.shape[0]
        with torch.enable_grad():
            # Each pixel's own copy of the lens centre, axes and the Gaussian's variance (see `_closed`).
            qq = q.clone().requires_grad_()
            cc = c.expand(n, 3).clone().requires_grad_()
            aa = a.expand(n, 2, 3).clone().requires_grad_()
            var = (psf.detach() ** 2).expand(n).clone().requires_grad_()
            dark = dark_fraction_lens_samples(self.target, qq, cc, aa, self.lens_xy, var)
            gq, gc, ga, gv = torch.autograd.grad(dark.sum(), (qq, cc, aa, var))
        return dark.detach(), torch.cat([chain(gq, gc, ga), (2.0 * psf.detach() * gv)[:, None]], 1)

    def _dark(self, v: int, geo: torch.Tensor, psf: torch.Tensor, jacobian: bool):
        """(N,) dark fractions of view v's pixels and (N, 11) their derivatives by (lens, pose, psf)."""
        dv = self.data[v]
        Ds, dDs = [], []
        # Pixels in three runs: closed form with SUBPIXELS_SHARP points a side, closed form with SUBPIXELS, samples.
        runs = ((0, dv.n_sharp, SUBPIXELS_SHARP), (dv.n_sharp, dv.n_closed_form, SUBPIXELS),
                (dv.n_closed_form, dv.uv.shape[0], None))
        focus = self._focus(v, geo, jacobian)
        for a in range(0, dv.uv.shape[0], JACOBIAN_BLOCK):
            b = min(a + JACOBIAN_BLOCK, dv.uv.shape[0])
            for lo, hi, sub in runs:
                lo, hi = max(lo, a), min(hi, b)
                if lo >= hi:
                    continue
                if sub is None:
                    D, dD = self._samples(focus, psf, dv.uv[lo:hi], jacobian)
                else:
                    D, dD = self._closed(focus, dv.uv[lo:hi], jacobian, sub)
                    dD = None if dD is None else torch.cat([dD, dD.new_zeros(hi - lo, 1)], 1)
                Ds.append(D)
                dDs.append(dD)
        return torch.cat(Ds), (torch.cat(dDs) if jacobian else None)

    # --- the solver's callback -------------------------------------------------------------------------------
    def evaluate(self, x: dict, with_jacobian: bool):
        lens, pose, levels = self.full_lens(x["lens"]), x["pose"], x["levels"]
        gain = x.get("gain")
        vig = x["vignetting"][0] if "vignetting" in x else torch.zeros((), dtype=torch.float64)
        psf = x["psf"][0] if "psf" in x else torch.tensor(self.psf_fixed, dtype=torch.float64)
        M = sum(int(d.uv.shape[0]) for d in self.data)
        stored = dict(zip(LENS_PARAMETERS, (float(v) for v in lens)))
        if not (stored["inv_U_per_m"] > 0 and stored["d_scaled"] > 0 and abs(stored["theta_F"]) < 1.5):
            nan = torch.full((M,), math.nan, dtype=torch.float64)   # outside the lens's domain
            sizes = {"lens": len(self.free), "pose": 6, "levels": 2, "vignetting": 1, "psf": 1, "gain": 2}
            return nan, ({k: nan[:, None].expand(M, sizes[k]) for k in x} if with_jacobian else None)
        rs, jac = [], {k: [] for k in x}
        for v, dv in enumerate(self.data):
            D, dD = self._dark(v, torch.cat([lens, pose[v]]), psf, with_jacobian)
            falloff = 1.0 - vig * dv.rho2
            if gain is not None:   # the illumination's gradient across the view: 1 + g_x x + g_y y
                falloff = falloff * (1.0 + dv.xy @ gain[v])
            white, black = levels[v, 0], levels[v, 1]
            shade = white - (white - black) * D
            rs.append((falloff * shade - dv.observed) / self.scale)
            if with_jacobian:
                Jg = (-falloff * (white - black) / self.scale)[:, None] * dD
                jac["lens"].append(Jg[:, :4] @ self.lens_jacobian(x["lens"]))
                if gain is not None:
                    jac["gain"].append(((1.0 - vig * dv.rho2) * shade / self.scale)[:, None] * dv.xy)
                jac["pose"].append(Jg[:, 4:10])
                jac["levels"].append(torch.stack([falloff * (1 - D), falloff * D], 1) / self.scale)
                if "vignetting" in jac:
                    g = 1.0 if gain is None else 1.0 + dv.xy @ gain[v]
                    jac["vignetting"].append((-dv.rho2 * g * shade / self.scale)[:, None])
                if "psf" in jac:
                    jac["psf"].append(Jg[:, 10:11])
        r = torch.cat(rs)
        if not with_jacobian:
            return r, None
        jac = {k: torch.cat(v) for k, v in jac.items()}
        self.n_jacobians += 1
        if self.say:
            cost = 0.5 * float((r * r).sum())
            _, U, d, theta_F = lens_values([float(v) for v in lens])
            self.say(f"photometric: linearisation {self.n_jacobians}, cost {cost:.6g}, θF "
                     f"{math.degrees(theta_F):+.4f}°, U {U:.2f} mm, d {d:.4f} mm "
                     f"({time.perf_counter() - self.t0:.1f} s)")
        return r, jac

    def residuals(self, x: dict) -> torch.Tensor:
        """(M,) residuals in linear intensity units."""
        with torch.no_grad():
            return self.evaluate(x, False)[0] * self.scale
