"""Rendering from regions: every pixel of a region is shaded along its region's beam, without ray casting.

A region's beam reflects from the mirrors of its signature and ends on its target face (or the background).
For each pixel the ray from the eye meets level j's face in that level's virtual scene (one plane equation,
no search); the point is moved back to the real scene and shaded there, with the integrator's model
(`renderer.scene.materials`):

    L = Σ_j T_j · (1 − r_j) · local_j  +  T_end · (background if the beam leaves the scene),
    T_0 = 1, T_{j+1} = T_j · r_j,

local = Σ_point lights [diffuse · albedo/π + Phong] · I·cos/d² · lit + Σ_ambient I · albedo.
Shadows come from beams too: `lit_regions` cuts from every face, once per light, the shadows that the
other faces cast on its plane (their polygons projected from the light), so a pixel is lit when its point
lies in its face's lit polygon.
"""
from __future__ import annotations

import math

import numpy as np
import shapely
import torch

from ..shapes.polyhedron import coordinates_across
from .polygons import EMPTY, areal, clip_halfspace, pyramid

# Shadow polygons are combined on this grid (scene units, in each face's plane): fixed-precision overlay
# is robust where the projected polygons nearly share edges.
SHADOW_GRID = 1e-10


def lit_regions(faces, lights) -> list[list]:
    """Per face, per light: the lit part of the face as a shapely geometry in its 2D frame.

    Ambient lights light everything (None). For a point light at P, face f (plane n·x = c) is unlit where
    n·P ≤ c; otherwise every other face g is clipped to the slab between f's plane and the plane through
    P parallel to it, projected from P onto f's plane, and subtracted.
    """
    out = []
    for f in faces:
        per_light = []
        for light in lights:
            if light.type != "point":
                per_light.append(None)
                continue
            P = np.asarray(light.position, dtype=np.float64)
            h = f.n @ P - f.c
            if h <= 0:
                per_light.append(EMPTY)
                continue
            tol = 1e-9 * (1.0 + abs(f.c))
            pyramid = _pyramid(f, P)
            shadows = []
            for g in faces:
                if g.index == f.index or (abs(abs(g.n @ f.n) - 1) < 1e-9 and abs(g.n @ f.o - g.c) < tol):
                    continue
                part = clip_halfspace(g.poly, g.o, g.u, g.v, -f.n, -(f.c + tol))  # in front of f's plane
                part = clip_halfspace(part, g.o, g.u, g.v, f.n, f.n @ P - tol)  # ... and before the light
                for a, b in pyramid:  # ... and between the light and f (so its shadow stays near f)
                    part = clip_halfspace(part, g.o, g.u, g.v, a, b)
                if part.is_empty:
                    continue
                st = shapely.get_coordinates(part)
                x = g.o + st[:, :1] * g.u + st[:, 1:2] * g.v
                k = h / (f.n @ P - x @ f.n)
                y = P + k[:, None] * (x - P)
                shadows.append(shapely.set_coordinates(part, np.stack([(y - f.o) @ f.u, (y - f.o) @ f.v], -1)))
            if shadows:
                # A face seen edge-on from the light projects to a degenerate ring: make_valid first.
                shadows = [areal(x) for x in shapely.make_valid(np.array(shadows, dtype=object))]
                shade = areal(shapely.union_all(shadows, grid_size=SHADOW_GRID))
                lit = f.poly if shade.is_empty else areal(shapely.difference(f.poly, shade, grid_size=SHADOW_GRID))
            else:
                lit = f.poly
            shapely.prepare(lit)
            per_light.append(lit)
        out.append(per_light)
    return out


def _pyramid(face, light: np.ndarray) -> list[tuple[np.ndarray, float]]:
    """Half-spaces a·x ≤ b whose intersection is the pyramid from the light through the face's bounding
    rectangle (in its plane, slightly enlarged): only what lies inside can shadow the face."""
    s0, t0, s1, t1 = face.poly.bounds
    pad = 1e-6 * (1.0 + max(s1 - s0, t1 - t0))
    corners = [face.o + s * face.u + t * face.v for s, t in ((s0 - pad, t0 - pad), (s1 + pad, t0 - pad),
                                                            (s1 + pad, t1 + pad), (s0 - pad, t1 + pad))]
    return pyramid(light, np.stack([q - light for q in corners]))


def shade_local(face, material, x: np.ndarray, d: np.ndarray, lights, lit: list, eps: float = 0.0) -> np.ndarray:
    """Local radiance (N, 3) leaving points x (N, 3) of `face` towards rays of direction d (N, 3).

    Args:
        material: the face's `renderer.scene.materials.Material`.
        lit: the face's lit polygons per light (`lit_regions`).
        eps: the ray tracer's offset of shadow-ray origins along the normal (`Scene.ray_epsilon`); the
            light's distance and direction are taken from there, as the integrator does.
    """
    n = face.n
    if material.texture is not None:
        p = torch.from_numpy(x)
        uv = coordinates_across(p, torch.full((x.shape[0],), int(np.abs(n).argmax()), dtype=torch.long))
        albedo = material.texture.evaluate(uv).numpy().astype(np.float64)
    else:
        albedo = np.broadcast_to(np.asarray(material.color, dtype=np.float64), x.shape)
    out = np.zeros_like(x)
    s, t = (x - face.o) @ face.u, (x - face.o) @ face.v
    for light, region in zip(lights, lit):
        intensity = np.asarray(light.intensity, dtype=np.float64)
        if light.type == "ambient":
            out += intensity * albedo
            continue
        if region.is_empty:
            continue
        to_light = np.asarray(light.position, dtype=np.float64) - (x + eps * n)
        dist2 = (to_light * to_light).sum(-1)
        l = to_light / np.sqrt(dist2)[:, None]
        cos = np.clip(l @ n, 0.0, None)
        scale = cos / np.maximum(dist2, 1e-30)
        if region is not face.poly:  # (the face's own polygon when nothing shadows it)
            scale = np.where(shapely.intersects_xy(region, s, t), scale, 0.0)
        shade = material.diffuse * albedo / math.pi
        if material.specular > 0:
            refl = 2 * cos[:, None] * n - l
            rv = np.clip(-(refl * d).sum(-1), 0.0, None)
            shade = shade + (material.specular * (material.shininess + 2) / (2 * math.pi)
                             * rv ** material.shininess)[:, None]
        out += shade * (intensity * scale[:, None])
    return out


def label_pixels(regions, width: int, height: int) -> np.ndarray:
    """(H, W) int: the region whose polygon holds each pixel centre (the first one for centres on a shared
    border; −1 where none does)."""
    labels = np.full((height, width), -1, dtype=np.int64)
    for k, r in enumerate(regions):
        x0, y0, x1, y1 = r.poly.bounds
        c0, c1 = max(0, math.ceil(x0)), min(width - 1, math.floor(x1))
        r0, r1 = max(0, math.ceil(y0)), min(height - 1, math.floor(y1))
        if c1 < c0 or r1 < r0:
            continue
        ys, xs = np.mgrid[r0:r1 + 1, c0:c1 + 1]
        shapely.prepare(r.poly)
        free = labels[r0:r1 + 1, c0:c1 + 1] < 0
        inside = shapely.intersects_xy(r.poly, xs[free].astype(np.float64), ys[free].astype(np.float64))
        block = labels[r0:r1 + 1, c0:c1 + 1]
        sub = block[free]
        sub[inside] = k
        block[free] = sub
    return labels


def render_regions(regions, labels: np.ndarray, cam, faces, materials, lights, lit, background,
                   eps: float = 0.0) -> np.ndarray:
    """(H, W, 3) linear RGB image from the regions (see the module docstring).

    Args:
        labels: `label_pixels(regions, W, H)`; materials: per face, its object's Material;
        background: linear RGB of beams that leave the scene; eps: see `shade_local`.
    """
    h, w = labels.shape
    image = np.zeros((h * w, 3))
    flat = labels.reshape(-1)
    order = np.argsort(flat, kind="stable")
    counts = np.bincount(flat + 1, minlength=len(regions) + 1)
    start = counts[0]
    background = np.asarray(background, dtype=np.float64)
    image[order[:start]] = background  # pixel centres in no region (none expected)
    # Walk every region's beam, collecting the real hit points per face; then shade each face once.
    hits: dict[int, list] = {}
    for k, region in enumerate(regions):
        pix = order[start:start + counts[k + 1]]
        start += counts[k + 1]
        if pix.size == 0:
            continue
        xy = np.stack([pix % w, pix // w], -1).astype(np.float64)
        d = cam.directions(xy)
        throughput = 1.0
        levels = list(region.signature) + [region.target]
        for face_id, (A, b) in zip(levels, region.transforms):
            if face_id < 0:
                image[pix] += throughput * background
                break
            f = faces[face_id]
            n_v = A @ f.n
            c_v = f.c + n_v @ b
            t = (c_v - n_v @ cam.eye) / (d @ n_v)
            x = (cam.eye + t[:, None] * d - b) @ A  # back to the real scene: A^T (x' − b)
            m = materials[face_id]
            hits.setdefault(face_id, []).append((pix, x, d @ A, throughput * (1.0 - m.reflect)))
            throughput *= m.reflect
    for face_id, parts in hits.items():
        pix = np.concatenate([p[0] for p in parts])
        x = np.concatenate([p[1] for p in parts])
        d = np.concatenate([p[2] for p in parts])
        weight = np.concatenate([np.full(p[0].size, p[3]) for p in parts])
        local = shade_local(faces[face_id], materials[face_id], x, d, lights, lit[face_id], eps)
        np.add.at(image, pix, weight[:, None] * local)  # a beam may meet one face more than once
    return image.reshape(h, w, 3)
