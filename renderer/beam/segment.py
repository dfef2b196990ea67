"""Steps (2)-(4) of the beam tracer: recursive screen segmentation, reused as the viewpoint moves.

Screen coordinates are pixels (x = column, y = row, (0, 0) the centre of the top-left pixel), so the
screen is the rectangle [−0.5, W − 0.5] × [−0.5, H − 0.5] of area W·H.

Mirroring keeps the eye E and the screen fixed and moves the scene instead: a beam that has reflected from
mirrors m1, m2, ... sees the scene transformed by M = S_k ∘ ... ∘ S_1 (S_i the reflection in the plane of
m_i as it appears after the earlier reflections), restricted to the far side of the last mirror's plane.
One `Node` per ray-tree signature (the tuple of mirror face ids) holds

- step (2), `determine`: the transformed candidate polygons (clipped to the far side of the mirror), the
  side of every candidate plane the eye is on (so which are front-facing: the visible-polygon
  candidates) and the pairwise occlusion order of the candidates, from plane-side tests alone;
- nothing of step (3), which `project_clip` redoes for each region and frame: project the front-facing
  candidates to the screen, clip them by the region (the polygon of interest), and cut each by the union
  of the candidates in front of it.

Both the front-facing set and the occlusion order depend on the eye only through the side of each
candidate plane it is on. When the viewpoint moves, a node is reused unless the eye crossed the infinite
plane of one of its candidates (the root node's candidates are the real polygons, so this includes every
real polygon plane); only then is step (2) redone, and only for that node. A crossing of a real polygon
plane (the paper's criterion) always re-determines the root; `BeamTracer.frame` reports it as
`redetermined`. The eye can also cross the plane of a mirrored polygon while crossing no real one (the
paper does not consider this); that re-determines just the node concerned (`Timing.nodes_redetermined`).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import shapely
from shapely.geometry import Polygon, box

from ..cameras.projection import project_pinhole
from camio.errors import SceneError
from .polygons import MIN_AREA, areal, clip_halfspace, polygons_of, pyramid

# The integrator drops paths whose throughput falls to this; the segmentation stops recursing there too.
MIN_THROUGHPUT = 1e-4
#: The most beams one segmentation may follow: lossless mirrors facing each other (a camera inside a box of
#: mirrors) multiply the beams with every reflection up to image.max_depth, past any time (each beam costs a few
#: milliseconds). The beam_fig2 scene makes at most 50 regions a frame.
MAX_BEAMS = 2000
# Screen-space clipping snaps to this grid (pixels): GEOS's fixed-precision overlay is robust, so regions
# stay an exact partition; without it, slivers between edges that should coincide (projected from two
# frames) left near-degenerate rings on which later overlays gave wrong areas.
SCREEN_GRID = 1e-9
# Eye closer to a candidate plane than this (scene units, relative to the scene size) counts as a crossing.
SIDE_TOL = 1e-9


@dataclass(frozen=True)
class ScreenCamera:
    """A pinhole camera as the segmentation sees it (world frame, scene units; pixels on the screen).

    Attributes:
        eye: (3,) viewpoint. world_from_camera: (3, 3), columns the camera x, y, z axes.
        width, height: pixels. center_px: principal point. pitch: scene units per pixel on the screen at
        `distance` from the eye.
    """

    eye: np.ndarray
    world_from_camera: np.ndarray
    width: int
    height: int
    center_px: tuple[float, float]
    pitch: tuple[float, float]
    distance: float

    @staticmethod
    def of(camera) -> "ScreenCamera":
        """From a renderer PinholeCamera without distortion (the segmentation projects straight lines)."""
        from ..cameras.pinhole import PinholeCamera
        from renderer.core.params import SceneError

        if not isinstance(camera, PinholeCamera):
            raise SceneError(f"camera.type: beam tracing needs a pinhole camera, got {type(camera).__name__}")
        if camera.distortion is not None and not camera.distortion.is_identity:
            raise SceneError("camera.distortion: beam tracing projects straight edges; it has no distortion model")
        s = camera.screen
        return ScreenCamera(camera.transform.position.numpy().astype(np.float64),
                            camera.transform.world_from_camera.numpy().astype(np.float64),
                            s.width_px, s.height_px, s.center_px, s.pitch, s.distance)

    def moved(self, distance: float) -> "ScreenCamera":
        """The camera moved by `distance` along its view direction."""
        return ScreenCamera(self.eye + distance * self.world_from_camera[:, 2], self.world_from_camera,
                            self.width, self.height, self.center_px, self.pitch, self.distance)

    @property
    def screen(self) -> Polygon:
        return box(-0.5, -0.5, self.width - 0.5, self.height - 0.5)

    def to_pixels(self, x_world: np.ndarray) -> np.ndarray:
        """(N, 3) world points in front of the eye -> (N, 2) pixels (central projection)."""
        p = (x_world - self.eye) @ self.world_from_camera
        return project_pinhole(p, (self.distance / self.pitch[0], self.distance / self.pitch[1]), self.center_px)

    def pyramid(self, bounds, pad_px: float = 1.0) -> list[tuple[np.ndarray, float]]:
        """Half-spaces a·x ≤ b (world) whose intersection is the pyramid from the eye through the screen
        rectangle `bounds` (x0, y0, x1, y1, pixels) grown by pad_px."""
        x0, y0, x1, y1 = bounds
        px = np.array([[x0 - pad_px, y0 - pad_px], [x1 + pad_px, y0 - pad_px], [x1 + pad_px, y1 + pad_px],
                       [x0 - pad_px, y1 + pad_px]])
        return pyramid(self.eye, self.directions(px))

    def directions(self, xy_px: np.ndarray) -> np.ndarray:
        """(N, 2) pixels -> (N, 3) unit world directions of the rays from the eye through them."""
        q = np.stack([(xy_px[:, 0] - self.center_px[0]) * self.pitch[0],
                      (xy_px[:, 1] - self.center_px[1]) * self.pitch[1],
                      np.full(xy_px.shape[0], self.distance)], -1)
        d = q @ self.world_from_camera.T
        return d / np.linalg.norm(d, axis=-1, keepdims=True)


@dataclass(frozen=True)
class Region:
    """One screen region: its pixels share one ray tree.

    Attributes:
        poly: shapely Polygon (holes allowed) in pixels.
        signature: face ids of the mirrors its beam reflects from, in order.
        target: face id its beam finally reaches (a diffuse face, or a mirror at the depth limit), −1 for
            the background.
        transforms: (A, b) per level (len(signature) + 1), x_virtual = A·x_real + b: level j sees face
            signature[j] (or the target at the last level) through this transform.
    """

    poly: Polygon
    signature: tuple[int, ...]
    target: int
    transforms: tuple = field(repr=False)


@dataclass
class Node:
    """Step (2) for one signature (see the module docstring). Arrays are over the m candidates."""

    signature: tuple[int, ...]
    A: np.ndarray
    b: np.ndarray
    ids: np.ndarray  # (m,) face ids
    polys: list  # m 2D polygons (clipped to the far side of the last mirror)
    O: np.ndarray  # (m, 3) frame origins, virtual
    U: np.ndarray
    V: np.ndarray
    N: np.ndarray  # (m, 3) outward normals, virtual
    C: np.ndarray  # (m,) plane offsets, virtual
    vertices: list  # m (k, 3) ring vertices, virtual
    vertex_array: np.ndarray | None = None  # the m vertex arrays concatenated
    vertex_start: np.ndarray | None = None  # (m,) where each candidate's vertices start in it
    side: np.ndarray | None = None  # (m,) bool: eye on the outer side (front-facing) at determination
    front_of: list | None = None  # per candidate: candidate indices certainly in front of it
    behind_of: list | None = None  # per candidate: candidate indices certainly behind it

    def eye_sides(self, eye: np.ndarray, tol: float) -> tuple[np.ndarray, np.ndarray]:
        """(m,) bool side of each candidate plane the eye is on, and (m,) whether it is within tol of it."""
        g = self.N @ eye - self.C
        return g > 0, np.abs(g) <= tol


def reflection(n: np.ndarray, c: float) -> tuple[np.ndarray, np.ndarray]:
    """(A, b) of the reflection in the plane n·x = c (n unit): x' = x − 2(n·x − c)n."""
    return np.eye(3) - 2 * np.outer(n, n), 2 * c * n


@dataclass
class Timing:
    """Seconds spent in each step during one `segment` call."""

    determine: float = 0.0  # step (2)
    project: float = 0.0  # step (3)
    nodes_built: int = 0  # new signatures: candidates moved and clipped
    nodes_ordered: int = 0  # front-facing sets and occlusion orders determined for new nodes
    nodes_redetermined: int = 0  # reused nodes whose own (possibly mirrored) candidate plane the eye crossed


class Segmenter:
    """Recursive screen segmentation of a scene of polygons (faces), with the node cache kept between calls.

    Args:
        faces: the scene's polygons (`polygons.scene_faces`).
        reflect: (F,) mirror weight of each face's material (0 for diffuse faces).
        max_depth: most reflections per beam (the scene's image.max_depth).
        extent: scene size, scene units (sets the plane-crossing tolerance).
    """

    def __init__(self, faces, reflect: np.ndarray, max_depth: int, extent: float = 1.0):
        self.faces = faces
        self._face_n = np.array([f.n for f in faces]).reshape(-1, 3)  # the real planes, for `crossed`
        self._face_c = np.array([f.c for f in faces])
        self._face_frames = np.array([[f.o, f.u, f.v, f.n] for f in faces], dtype=np.float64).reshape(-1, 4, 3)
        self.reflect = np.asarray(reflect, dtype=np.float64)
        self.max_depth = max_depth
        self.tol = SIDE_TOL * (1.0 + extent)
        self.nodes: dict[tuple[int, ...], Node] = {}
        self.timing = Timing()

    # ------------------------------------------------------------------------------------------- step (2)

    def _build(self, signature: tuple[int, ...]) -> Node:
        """Candidates of a signature: every face moved by the signature's mirrors, clipped behind the last."""
        if not signature:
            A, b = np.eye(3), np.zeros(3)
            mirror = None
        else:
            parent = self.node(signature[:-1])
            k = int(np.nonzero(parent.ids == signature[-1])[0][0])
            n_m, c_m = parent.N[k], parent.C[k]
            S, s = reflection(n_m, c_m)
            A, b = S @ parent.A, S @ parent.b + s
            mirror = (n_m, c_m)
        ids, polys, O, U, V, N, C, verts = [], [], [], [], [], [], [], []
        frames = self._face_frames @ A.T  # (F, 4, 3): every face's o, u, v, n moved by A at once
        for f, (o, u, v, n) in zip(self.faces, frames):
            o = o + b
            c = float(n @ o)
            poly = f.poly
            if mirror is not None:
                n_m, c_m = mirror
                if abs(abs(n @ n_m) - 1) < 1e-9 and abs(c - np.sign(n @ n_m) * c_m) < self.tol:
                    continue  # in the mirror's plane: reflected rays leave it
                # Rays reflected by the mirror travel into its front side, which S maps behind it.
                poly = clip_halfspace(poly, o, u, v, n_m, c_m)
                if poly.area <= MIN_AREA:
                    continue
            ids.append(f.index)
            polys.append(poly)
            O.append(o), U.append(u), V.append(v), N.append(n), C.append(c)
            coords = shapely.get_coordinates(poly)
            verts.append(o + coords[:, :1] * u + coords[:, 1:2] * v)
        node = Node(signature, A, b, np.array(ids, dtype=np.int64), polys, np.array(O).reshape(-1, 3),
                    np.array(U).reshape(-1, 3), np.array(V).reshape(-1, 3), np.array(N).reshape(-1, 3),
                    np.array(C), verts)
        node.vertex_array = np.concatenate(verts) if verts else np.zeros((0, 3))
        node.vertex_start = np.cumsum([0] + [len(v) for v in verts[:-1]]).astype(np.int64)
        self.timing.nodes_built += 1
        return node

    def _order(self, node: Node, eye: np.ndarray) -> None:
        """Front-facing candidates and their pairwise occlusion order for an eye (step (2) proper).

        Candidate a is certainly in front of b (a hides b wherever their projections overlap) when every
        vertex of a lies on the eye's side of b's plane, or every vertex of b on the far side of a's plane.
        """
        side, _ = node.eye_sides(eye, self.tol)
        node.side = side
        m = len(node.ids)
        if m == 0:
            node.front_of, node.behind_of = [], []
            return
        g_eye = node.N @ eye - node.C  # (m,)
        # Every candidate's vertices against every plane, signed so that > 0 is the eye's side: (K, m).
        toward = (node.vertex_array @ node.N.T - node.C) * np.sign(g_eye)
        tol = self.tol
        on_eye_side = np.logical_and.reduceat(toward >= -tol, node.vertex_start, axis=0)  # (m, m): a vs plane b
        behind = np.logical_and.reduceat(toward <= tol, node.vertex_start, axis=0)
        # a wholly on the eye's side of b's plane: a in front of b; a wholly behind it: b in front of a.
        ahead = on_eye_side | behind.T
        np.fill_diagonal(ahead, False)
        certain = ahead & ~ahead.T
        node.front_of = [np.nonzero(certain[:, a])[0] for a in range(m)]
        node.behind_of = [np.nonzero(certain[a])[0] for a in range(m)]

    def node(self, signature: tuple[int, ...], eye: np.ndarray | None = None) -> Node:
        """The cached node for a signature, built if new; with `eye`, re-determined if the eye crossed one
        of its candidate planes since it was determined."""
        node = self.nodes.get(signature)
        if node is None:
            node = self._build(signature)
            self.nodes[signature] = node
        if eye is not None:
            if node.side is None:
                self._order(node, eye)
                self.timing.nodes_ordered += 1
            else:
                side, near = node.eye_sides(eye, self.tol)
                if (side != node.side).any() or near.any():
                    self._order(node, eye)
                    self.timing.nodes_redetermined += 1
        return node

    def crossed(self, eye_from: np.ndarray, eye_to: np.ndarray) -> np.ndarray:
        """Face ids whose (real) infinite plane the eye crosses or touches moving from eye_from to eye_to."""
        a, b = self._face_n @ eye_from - self._face_c, self._face_n @ eye_to - self._face_c
        return np.nonzero(((a > 0) != (b > 0)) | (np.abs(b) <= self.tol))[0]

    # ------------------------------------------------------------------------------------------- step (3)

    def project_clip(self, node: Node, region: Polygon, cam: ScreenCamera) -> list[tuple[int, object]]:
        """Visible parts of the node's candidates inside `region`, and the background part.

        Returns:
            [(candidate index or −1 for the background, shapely geometry in pixels)], disjoint, covering
            `region`.
        """
        front = np.nonzero(node.side)[0]
        if front.size == 0:
            return [(-1, region)]
        polys = [node.polys[i] for i in front]
        # Parts behind the eye never reach the screen, and parts near the eye's plane project far away (where
        # the overlay grid loses precision): such candidates are first cut to the view pyramid of the region.
        view = cam.world_from_camera[:, 2]
        near = 1e-9 * (1.0 + np.abs(cam.eye).max()) + cam.distance * 1e-6
        far_px = 1e3 * (cam.width + cam.height)
        pyramid = None
        with np.errstate(divide="ignore", invalid="ignore"):
            depth = (node.vertex_array - cam.eye) @ view
            px = np.abs(cam.to_pixels(node.vertex_array)).max(-1)
        bad = np.logical_or.reduceat((depth < near) | ~(px <= far_px), node.vertex_start)
        for j, i in enumerate(front):
            if not bad[i]:
                continue
            if pyramid is None:
                pyramid = cam.pyramid(region.bounds, pad_px=1.0) + [(-view, -(cam.eye @ view + near))]
            for a, b in pyramid:
                polys[j] = clip_halfspace(polys[j], node.O[i], node.U[i], node.V[i], a, b)
        geoms = np.array(polys, dtype=object)
        keep = ~shapely.is_empty(geoms)
        front, geoms = front[keep], geoms[keep]
        if front.size == 0:
            return [(-1, region)]
        st, idx = shapely.get_coordinates(geoms, return_index=True)
        world = node.O[front][idx] + st[:, :1] * node.U[front][idx] + st[:, 1:2] * node.V[front][idx]
        screen = shapely.set_coordinates(geoms.copy(), cam.to_pixels(world))
        # Only candidates whose bounding box meets the region's can be seen in it.
        x0, y0, x1, y1 = region.bounds
        b = shapely.bounds(screen)
        meets = (b[:, 0] <= x1) & (b[:, 2] >= x0) & (b[:, 1] <= y1) & (b[:, 3] >= y0)
        front, screen = front[meets], screen[meets]
        if front.size == 0:
            return [(-1, region)]
        screen = np.array([areal(g) for g in shapely.make_valid(screen)], dtype=object)
        clipped = shapely.intersection(screen, region, grid_size=SCREEN_GRID)
        keep = shapely.area(clipped) > MIN_AREA
        front = front[keep]
        clipped = np.array([areal(g) for g in clipped[keep]], dtype=object)
        if front.size == 0:
            return [(-1, region)]
        tree = shapely.STRtree(clipped)
        left, right = tree.query(clipped, predicate="intersects")
        cover: list[list[int]] = [[] for _ in front]
        for a, b in zip(left.tolist(), right.tolist()):
            if a >= b:
                continue
            ca, cb = int(front[a]), int(front[b])
            if cb in node.front_of[ca]:
                cover[a].append(b)
            elif cb in node.behind_of[ca]:
                cover[b].append(a)
            else:  # no plane separates them: compare depths at a point of their overlap
                overlap = shapely.intersection(clipped[a], clipped[b], grid_size=SCREEN_GRID)
                if shapely.area(overlap) <= MIN_AREA:
                    continue
                p = shapely.get_coordinates(shapely.point_on_surface(overlap))
                d = cam.directions(p)[0]
                ta = (node.C[ca] - node.N[ca] @ cam.eye) / (node.N[ca] @ d)
                tb = (node.C[cb] - node.N[cb] @ cam.eye) / (node.N[cb] @ d)
                (cover[a] if tb < ta else cover[b]).append(b if tb < ta else a)
        pieces = []
        for j in range(front.size):
            geom = clipped[j]
            if cover[j]:
                geom = areal(shapely.difference(geom, shapely.union_all(clipped[cover[j]], grid_size=SCREEN_GRID),
                                                grid_size=SCREEN_GRID))
            pieces.append((int(front[j]), geom))
        pieces.append((-1, areal(shapely.difference(region, shapely.union_all(clipped, grid_size=SCREEN_GRID),
                                                    grid_size=SCREEN_GRID))))
        return pieces

    # ------------------------------------------------------------------------------------------- step (4)

    def segment(self, cam: ScreenCamera) -> list[Region]:
        """Regions of the whole screen for a camera (steps (2)-(4)), reusing cached nodes where valid."""
        self.timing = Timing()
        regions: list[Region] = []
        stack = [((), cam.screen, 1.0, ((np.eye(3), np.zeros(3)),))]
        beams = 0
        while stack:
            beams += 1
            if beams > MAX_BEAMS:
                raise SceneError(f"image.max_depth: {self.max_depth} reflections make more than {MAX_BEAMS} beams "
                                 "(mirrors that lose little light face each other); lower image.max_depth or the "
                                 "mirrors' reflect")
            signature, area, throughput, transforms = stack.pop()
            t0 = time.perf_counter()
            node = self.node(signature, cam.eye)
            t1 = time.perf_counter()
            pieces = self.project_clip(node, area, cam)
            t2 = time.perf_counter()
            self.timing.determine += t1 - t0
            self.timing.project += t2 - t1
            for k, geom in pieces:
                face = -1 if k < 0 else int(node.ids[k])
                for poly in polygons_of(geom):
                    r = self.reflect[face] if face >= 0 else 0.0
                    if r > 0 and len(signature) < self.max_depth and throughput * r > MIN_THROUGHPUT:
                        child = signature + (face,)
                        n_m, c_m = node.N[k], node.C[k]
                        S, s = reflection(n_m, c_m)
                        stack.append((child, poly, throughput * r, transforms + ((S @ node.A, S @ node.b + s),)))
                    else:
                        regions.append(Region(poly, signature, face, transforms))
        return regions
