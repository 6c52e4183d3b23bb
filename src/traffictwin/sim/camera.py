"""Hood-mounted rectified stereo camera rendered from the box world (paper 003, section 3.3).

Two identical pinhole cameras on the hood, same orientation (looking along the vehicle's +x,
no roll/pitch), same height, ``baseline`` metres apart laterally (left eye at ``+B/2`` in the
vehicle's +y, right eye at ``-B/2``). Images are rectified by construction: a world point
appears in the same row of both images and its disparity is ``u_L - u_R = fx * B / Z`` (Z =
depth along the optical axis, m).

Rendering is a z-buffer rasteriser (no per-pixel Python loops):

* the ground plane ``z = 0`` is solved analytically per pixel (depth ``h * fy / (v - cy)``);
* every front-facing face of every box inside the view frustum is clipped at the near plane,
  filled with ``cv2.fillConvexPoly`` (sub-pixel, ``shift=4``) into a mask of its bounding
  rectangle, its exact depth per pixel computed from its plane, and merged into the z-buffer
  (a loop over faces, vectorised over pixels);
* colour = procedural texture that is a function of the surface point (box-local coordinates
  for boxes, so a moving car carries its pattern; world coordinates and a lane-marking raster
  for the ground), so both eyes see the same pattern, times Lambertian shading; sky is a
  gradient; then Gaussian sensor noise.

Coordinates: camera frame X right, Y down, Z forward (m); pixel centres at integer (u, v).
Vehicle frame x forward, y left, z up; the vehicle pose is (x, y, yaw) in the world (m, rad)
of its reference point (footprint centre).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass
from typing import Any

import cv2
import numpy as np

from traffictwin.sim.scene import Boxes, Cls

_SHIFT = 4  # fillConvexPoly fixed-point bits (1/16 px)

# base colours (BGR, 0..1) per class
_CLASS_BGR = {
    int(Cls.CAR): (0.35, 0.25, 0.75),
    int(Cls.TRUCK): (0.55, 0.55, 0.35),
    int(Cls.MOTORCYCLE): (0.2, 0.2, 0.25),
    int(Cls.PEDESTRIAN): (0.3, 0.45, 0.6),
    int(Cls.BUILDING): (0.6, 0.65, 0.7),
    int(Cls.WALL): (0.5, 0.55, 0.6),
    int(Cls.VEGETATION): (0.2, 0.5, 0.25),
    int(Cls.POLE): (0.45, 0.45, 0.45),
}
_SUN = np.array([0.35, 0.45, 0.82])
_SUN = _SUN / np.linalg.norm(_SUN)


@dataclass(frozen=True)
class StereoCamera:
    """Rectified pinhole stereo pair.

    width, height: image size (px); hfov_deg: horizontal field of view (deg); square pixels
    (fy = fx); baseline (m); mount_x: optical centres' position ahead of the vehicle
    reference point (m); mount_height: above ground (m); near: near clipping plane (m);
    max_range: boxes beyond this depth are not drawn (m); noise_std: Gaussian sensor noise (DN).
    """

    width: int = 320
    height: int = 160
    hfov_deg: float = 60.0
    baseline: float = 0.16
    mount_x: float = 1.2
    mount_height: float = 1.3
    near: float = 0.2
    max_range: float = 100.0
    noise_std: float = 2.0

    def __post_init__(self) -> None:
        if self.width < 8 or self.height < 8:
            raise ValueError(f"camera width/height must be >= 8 px, got {self.width}x{self.height}")
        if not 5.0 <= self.hfov_deg <= 150.0:
            raise ValueError(f"camera hfov_deg must be in [5, 150] deg, got {self.hfov_deg}")
        if (
            self.baseline <= 0
            or self.mount_height <= 0
            or self.near <= 0
            or self.max_range <= self.near
        ):
            raise ValueError(
                "camera baseline, mount_height, near must be > 0 and max_range > near (m)"
            )
        object.__setattr__(
            self, "_fx", float((self.width / 2.0) / np.tan(np.radians(self.hfov_deg) / 2.0))
        )

    @property
    def fx(self) -> float:
        """Focal length (px)."""
        return self._fx  # type: ignore[attr-defined]

    @property
    def fy(self) -> float:
        return self.fx

    @property
    def cx(self) -> float:
        return self.width / 2.0 - 0.5

    @property
    def cy(self) -> float:
        return self.height / 2.0 - 0.5

    def intrinsics(self) -> dict[str, float]:
        """The manifest's ``camera`` entry: width, height, fx, fy, cx, cy, baseline, mounts (px, m)."""
        d = {k: float(v) if not isinstance(v, int) else v for k, v in asdict(self).items()}
        d.update(fx=float(self.fx), fy=float(self.fy), cx=float(self.cx), cy=float(self.cy))
        return d

    def disparity_from_depth(self, depth: np.ndarray) -> np.ndarray:
        """GT disparity ``fx * B / Z`` (px); 0 where there is no surface (depth inf)."""
        d = np.zeros(depth.shape, np.float32)
        ok = np.isfinite(depth) & (depth > 0)
        d[ok] = (self.fx * self.baseline / depth[ok]).astype(np.float32)
        return d

    def eye_pose(self, pose: Sequence[float], eye: str) -> tuple[np.ndarray, float]:
        """World (x, y, z) of an eye's optical centre and the yaw (rad); eye 'left' | 'right'."""
        if eye not in ("left", "right"):
            raise ValueError(f"eye must be 'left' or 'right', got {eye!r}")
        x, y, yaw = (float(p) for p in pose)
        lat = self.baseline / 2.0 if eye == "left" else -self.baseline / 2.0
        c, s = np.cos(yaw), np.sin(yaw)
        return np.array(
            [x + c * self.mount_x - s * lat, y + s * self.mount_x + c * lat, self.mount_height]
        ), yaw

    def rays(self, cy_offset: float = 0.0) -> np.ndarray:
        """Per-pixel ray directions in the camera frame scaled to unit depth (H, W, 3): (X/Z, Y/Z, 1)."""
        u = (np.arange(self.width) - self.cx) / self.fx
        v = (np.arange(self.height) - (self.cy + cy_offset)) / self.fy
        uu, vv = np.meshgrid(u, v)
        return np.stack([uu, vv, np.ones_like(uu)], -1)

    # ------------------------------------------------------------------------------------------
    def render_eye(
        self,
        pose: Sequence[float],
        boxes: Boxes,
        ground: GroundTexture | None = None,
        eye: str = "left",
        cy_offset: float = 0.0,
        rng: np.random.Generator | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Render one eye: BGR uint8 image (H, W, 3) and depth Z (H, W) float32 (m, inf = sky).

        pose: vehicle (x, y, yaw) in the world (m, rad); boxes: world boxes (agents + static);
        cy_offset: shifts the principal point down by this many px (a vertical misalignment
        fault); rng: sensor-noise generator (None = no noise).
        """
        H, W = self.height, self.width
        centre, yaw = self.eye_pose(pose, eye)
        # world -> camera rotation: camera X = -vehicle y, Y = -z, Z = vehicle x
        c, s = np.cos(yaw), np.sin(yaw)
        R = np.array([[s, -c, 0.0], [0.0, 0.0, -1.0], [c, s, 0.0]])
        d = self.rays(cy_offset)  # (H, W, 3)

        # ground plane: camera Y = +h (down); depth Z = h / (v - cy)/fy
        dv = d[..., 1]
        zbuf = np.full((H, W), np.inf)
        below = dv > 1e-9
        zbuf[below] = self.mount_height / dv[below]
        face = np.full((H, W), -1, np.int64)  # -1 ground (where finite), >=0 face index
        faces = _box_faces(boxes)
        vis = np.flatnonzero(self._cull(faces, centre, R))
        if len(vis):
            cy_eff = self.cy + cy_offset
            pc_all = (faces.verts[vis] - centre) @ R.T  # (F, 4, 3) camera frame
            n_all = faces.normal[vis] @ R.T  # plane normals in the camera frame
            c_all = np.einsum("fk,fk->f", n_all, pc_all[:, 0])
            straddle = (pc_all[..., 2] < self.near).any(1)
            z = np.maximum(pc_all[..., 2], 1e-9)
            u_all = self.cx + self.fx * pc_all[..., 0] / z
            v_all = cy_eff + self.fy * pc_all[..., 1] / z
            for j in range(len(vis)):  # loop over faces; pixels are vectorised
                if straddle[j]:
                    poly = _clip_near(pc_all[j], self.near)
                    if len(poly) < 3:
                        continue
                    u = self.cx + self.fx * poly[:, 0] / poly[:, 2]
                    v = cy_eff + self.fy * poly[:, 1] / poly[:, 2]
                else:
                    u, v = u_all[j], v_all[j]
                self._raster_face(u, v, n_all[j], c_all[j], int(vis[j]), d, zbuf, face)

        # colour
        img = np.empty((H, W, 3), np.float32)
        sky = ~np.isfinite(zbuf)
        if sky.any():
            rows = np.clip((np.arange(H, dtype=np.float32) - (self.cy + cy_offset)) / H, -1, 1)[
                :, None
            ]
            sky_col = np.stack(
                [0.95 - 0.2 * rows, 0.8 - 0.1 * rows, 0.6 + 0.1 * rows], -1
            ) * np.ones((1, W, 1), np.float32)
            img[sky] = sky_col[sky]
        g = (face < 0) & ~sky
        b = face >= 0
        if g.any():
            pw = (d[g] * zbuf[g][:, None]) @ R + centre  # world points (world = R^T pc + centre)
            img[g] = (ground or GroundTexture.plain()).sample(pw[:, 0], pw[:, 1])
        if b.any():
            pw = (d[b] * zbuf[b][:, None]) @ R + centre
            img[b] = _box_colour(faces, face[b], pw, boxes)
        img *= 255.0
        if rng is not None and self.noise_std > 0:
            img += rng.standard_normal(img.shape, dtype=np.float32) * np.float32(self.noise_std)
        depth = zbuf.astype(np.float32)
        return np.clip(np.rint(img), 0, 255).astype(np.uint8), depth

    def _cull(self, faces: _Faces, centre: np.ndarray, R: np.ndarray) -> np.ndarray:
        """Front-facing faces with some vertex inside the (near, max_range) depth slab and frustum."""
        if len(faces.normal) == 0:
            return np.zeros(0, bool)
        front = np.einsum("fk,fk->f", faces.normal, centre - faces.verts[:, 0]) > 1e-9
        pc = (faces.verts - centre) @ R.T  # (F, 4, 3) camera frame
        Z = pc[..., 2]
        in_depth = (Z.max(1) > self.near) & (Z.min(1) < self.max_range)
        tx = np.tan(np.radians(self.hfov_deg) / 2.0) * 1.05
        zc = np.maximum(Z, 1e-6)
        left_out = np.all((pc[..., 0] < -tx * zc) & (Z > 0), 1)
        right_out = np.all((pc[..., 0] > tx * zc) & (Z > 0), 1)
        return front & in_depth & ~left_out & ~right_out

    def _raster_face(
        self,
        u: np.ndarray,
        v: np.ndarray,
        n_c: np.ndarray,
        c: float,
        fi: int,
        d: np.ndarray,
        zbuf: np.ndarray,
        face: np.ndarray,
    ) -> None:
        """Fill the projected polygon (u, v) (px) of face ``fi`` (plane n_c . X = c, camera
        frame) into the z-buffer with its exact per-pixel depth."""
        H, W = zbuf.shape
        x0, x1 = int(np.floor(max(u.min(), 0))), int(np.ceil(min(u.max(), W - 1))) + 1
        y0, y1 = int(np.floor(max(v.min(), 0))), int(np.ceil(min(v.max(), H - 1))) + 1
        if x1 <= x0 or y1 <= y0:
            return
        mask = np.zeros((y1 - y0, x1 - x0), np.uint8)
        pts = np.round(np.stack([u - x0, v - y0], 1) * (1 << _SHIFT))
        pts = np.clip(pts, -(1 << 26), 1 << 26).astype(np.int32)
        cv2.fillConvexPoly(mask, pts, 1, lineType=cv2.LINE_8, shift=_SHIFT)
        m = mask.view(bool)
        dd = d[y0:y1, x0:x1]
        den = dd[..., 0] * n_c[0] + dd[..., 1] * n_c[1] + n_c[2]
        with np.errstate(divide="ignore", invalid="ignore"):
            Z = c / den
        zb = zbuf[y0:y1, x0:x1]
        upd = m & (Z > self.near * 0.5) & (Z < zb)
        zb[upd] = Z[upd]
        face[y0:y1, x0:x1][upd] = fi

    def render_pair(
        self,
        pose: Sequence[float],
        boxes: Boxes,
        ground: GroundTexture | None = None,
        pose_right: Sequence[float] | None = None,
        boxes_right: Boxes | None = None,
        right_cy_offset: float = 0.0,
        rng: np.random.Generator | None = None,
    ) -> dict[str, np.ndarray]:
        """Left and right images, left depth and GT disparity of one stereo frame.

        ``pose_right``/``boxes_right`` (default: the left ones) render the right eye at another
        time (the delayed-frame fault); ``right_cy_offset`` (px) a vertical misalignment.
        Returns ``left``, ``right`` (H, W, 3) uint8 BGR, ``depth`` (H, W) float32 m (inf = sky),
        ``disp_gt`` (H, W) float32 px (0 = no surface).
        """
        left, depth = self.render_eye(pose, boxes, ground, "left", 0.0, rng)
        right, _ = self.render_eye(
            pose if pose_right is None else pose_right,
            boxes if boxes_right is None else boxes_right,
            ground,
            "right",
            right_cy_offset,
            rng,
        )
        return {
            "left": left,
            "right": right,
            "depth": depth,
            "disp_gt": self.disparity_from_depth(depth),
        }


# ------------------------------------------------------------------------------------------------
@dataclass
class _Faces:
    verts: np.ndarray  # (F, 4, 3) world
    normal: np.ndarray  # (F, 3) outward unit
    box: np.ndarray  # (F,) box index
    kind: np.ndarray  # (F,) 0..3 side (edge k), 4 top


def _box_faces(boxes: Boxes) -> _Faces:
    """Four side faces and the top face of every box (bottoms are never seen from above)."""
    n = len(boxes)
    if n == 0:
        return _Faces(
            np.zeros((0, 4, 3)), np.zeros((0, 3)), np.zeros(0, np.int64), np.zeros(0, np.int64)
        )
    cr = boxes.corners()  # (N, 4, 2) CCW
    z0 = boxes.z0[:, None]
    z1 = (boxes.z0 + boxes.size[:, 2])[:, None]
    a = cr
    b = np.roll(cr, -1, axis=1)
    side = np.stack(
        [
            np.concatenate([a, np.broadcast_to(z0, (n, 4))[..., None]], -1),
            np.concatenate([b, np.broadcast_to(z0, (n, 4))[..., None]], -1),
            np.concatenate([b, np.broadcast_to(z1, (n, 4))[..., None]], -1),
            np.concatenate([a, np.broadcast_to(z1, (n, 4))[..., None]], -1),
        ],
        2,
    )  # (N, 4 faces, 4 verts, 3)
    e = b - a
    nrm = np.stack([e[..., 1], -e[..., 0], np.zeros((n, 4))], -1)
    nrm /= np.linalg.norm(nrm, axis=-1, keepdims=True)
    top = np.concatenate([cr, np.broadcast_to(z1, (n, 4))[..., None]], -1)[:, None]  # (N,1,4,3)
    verts = np.concatenate([side, top], 1).reshape(-1, 4, 3)
    normal = np.concatenate([nrm, np.broadcast_to([0.0, 0.0, 1.0], (n, 1, 3))], 1).reshape(-1, 3)
    box = np.repeat(np.arange(n), 5)
    kind = np.tile(np.arange(5), n)
    return _Faces(verts, normal, box, kind)


def _clip_near(poly: np.ndarray, near: float) -> np.ndarray:
    """Sutherland-Hodgman clip of a convex polygon (M, 3) (camera frame) to Z >= near."""
    inside = poly[:, 2] >= near
    if inside.all():
        return poly
    if not inside.any():
        return poly[:0]
    out = []
    m = len(poly)
    for i in range(m):  # at most 4-5 vertices: a loop over polygon vertices, not pixels
        p, q = poly[i], poly[(i + 1) % m]
        pin, qin = p[2] >= near, q[2] >= near
        if pin:
            out.append(p)
        if pin != qin:
            t = (near - p[2]) / (q[2] - p[2])
            out.append(p + t * (q - p))
    return np.array(out)


# ------------------------------------------------------------------------------------------------
def _hash01(ix: np.ndarray, iy: np.ndarray, seed: np.ndarray | int) -> np.ndarray:
    """Deterministic integer hash of lattice points -> [0, 1)."""
    with np.errstate(over="ignore"):
        return _hash01_impl(
            np.atleast_1d(ix), np.atleast_1d(iy), np.atleast_1d(np.asarray(seed, np.int64))
        )


def _hash01_impl(ix: np.ndarray, iy: np.ndarray, seed: np.ndarray) -> np.ndarray:
    h = ix.astype(np.int64).astype(np.uint32) * np.uint32(0x8DA6B343)
    h ^= iy.astype(np.int64).astype(np.uint32) * np.uint32(0xD8163841)
    h ^= (seed.astype(np.uint32) + np.uint32(0x9E3779B9)) * np.uint32(0xCB1AB31F)
    h ^= h >> np.uint32(13)
    h *= np.uint32(0x5BD1E995)
    h ^= h >> np.uint32(15)
    return h.astype(np.float64) / 4294967296.0


def value_noise(
    a: np.ndarray,
    b: np.ndarray,
    seed: np.ndarray | int,
    scales: Sequence[float],
    weights: Sequence[float],
) -> np.ndarray:
    """Multi-octave value noise of surface coordinates (a, b) in metres; output in [0, 1].

    scales: lattice spacing per octave (m); weights: their amplitudes (normalised).
    """
    out = np.zeros(np.shape(a))
    for k, (sc, w) in enumerate(zip(scales, weights)):
        x, y = a / sc, b / sc
        ix, iy = np.floor(x), np.floor(y)
        fx, fy = x - ix, y - iy
        fx = fx * fx * (3 - 2 * fx)
        fy = fy * fy * (3 - 2 * fy)
        sd = np.asarray(seed, np.int64) * 7 + k
        v00 = _hash01(ix, iy, sd)
        v10 = _hash01(ix + 1, iy, sd)
        v01 = _hash01(ix, iy + 1, sd)
        v11 = _hash01(ix + 1, iy + 1, sd)
        out += w * ((v00 * (1 - fx) + v10 * fx) * (1 - fy) + (v01 * (1 - fx) + v11 * fx) * fy)
    return out / float(sum(weights))


def _box_colour(faces: _Faces, fidx: np.ndarray, pw: np.ndarray, boxes: Boxes) -> np.ndarray:
    """Colour (P, 3) in [0, 1] of box surface points ``pw`` (P, 3) world on faces ``fidx``."""
    bi = faces.box[fidx]
    kind = faces.kind[fidx]
    yaw = boxes.yaw[bi]
    c, s = np.cos(yaw), np.sin(yaw)
    dx, dy = pw[:, 0] - boxes.center[bi, 0], pw[:, 1] - boxes.center[bi, 1]
    lx, ly = c * dx + s * dy, -s * dx + c * dy  # box-local (m)
    lz = pw[:, 2] - boxes.z0[bi]
    # side faces 0/2 (left/right) run along local x, 1/3 (rear/front) along local y; top uses (lx, ly)
    a = np.where(kind % 2 == 0, lx, ly)
    a = np.where(kind == 4, lx, a)
    b = np.where(kind == 4, ly, lz)
    seed = boxes.ids[bi] * 5 + kind + boxes.cls[bi] * 100003
    tex = value_noise(a, b, seed, (0.07, 0.22, 0.9), (0.45, 0.35, 0.2))
    base = np.array([_CLASS_BGR.get(int(k), (0.5, 0.5, 0.5)) for k in range(8)])[
        np.clip(boxes.cls[bi], 0, 7)
    ]
    vehicle = np.isin(boxes.cls[bi], [int(Cls.CAR), int(Cls.TRUCK), int(Cls.MOTORCYCLE)])[:, None]
    hue = np.stack([_hash01(boxes.ids[bi], boxes.cls[bi], 17 + j) for j in range(3)], 1)
    tint = np.where(vehicle, 0.3 + 1.6 * hue, 0.8 + 0.4 * hue[:, :1])
    shade = 0.45 + 0.55 * np.clip(faces.normal[fidx] @ _SUN, 0, 1)
    col = base * tint * (0.35 + 0.9 * tex)[:, None] * shade[:, None]
    return np.clip(col, 0, 1)


@dataclass(frozen=True)
class GroundStyle:
    """Ground raster layout: margin around the drawn lines (m), lane-edge dashes (on, off) (m),
    marking width (m) and the width of sidewalk polylines (m)."""

    margin: float = 20.0
    dash: tuple[float, float] = (3.0, 6.0)
    marking_width: float = 0.15
    sidewalk_width: float = 2.5


class _Canvas:
    """A uint8 surface-type raster (row = y, col = x) covering ``[lo, hi]`` (m) at ``res`` m/px."""

    def __init__(self, lo: np.ndarray, hi: np.ndarray, res: float) -> None:
        self.lo, self.res = lo, res
        Wr, Hr = int(np.ceil((hi[0] - lo[0]) / res)), int(np.ceil((hi[1] - lo[1]) / res))
        self.raster = np.zeros((Hr, Wr), np.uint8)

    def line(self, poly: Any, closed: bool, value: int, width: float) -> None:
        """Draw polyline ``poly`` (M, 2; m) ``width`` m wide (at least 1 px) with ``value``."""
        px = np.round((np.asarray(poly, float) - self.lo) / self.res * (1 << _SHIFT))
        cv2.polylines(
            self.raster,
            [px.astype(np.int32)],
            closed,
            value,
            thickness=max(1, int(round(width / self.res))),
            shift=_SHIFT,
        )


class GroundTexture:
    """Ground colour as a function of the world point: a raster of surface types + noise.

    Surface types (uint8 raster at ``res`` m/px, world origin ``origin`` = (x_min, y_min)):
    0 terrain, 1 road (asphalt), 2 lane marking, 3 sidewalk. Outside the raster: terrain.
    """

    _COL = np.array([[0.25, 0.45, 0.4], [0.36, 0.37, 0.38], [0.9, 0.92, 0.93], [0.6, 0.62, 0.65]])

    def __init__(
        self, raster: np.ndarray, origin: Sequence[float], res: float, seed: int = 0
    ) -> None:
        self.raster = np.asarray(raster, np.uint8)
        self.origin = np.asarray(origin, float)
        self.res = float(res)
        self.seed = int(seed)

    @staticmethod
    def plain() -> GroundTexture:
        """Asphalt everywhere (no markings)."""
        return GroundTexture(np.ones((1, 1), np.uint8), (-1e9, -1e9), 2e9)

    @staticmethod
    def from_world(world: object, res: float = 0.1, seed: int = 0) -> GroundTexture:
        """Ground of a :class:`~traffictwin.sim.world.World`: roads (``half_width``), sidewalks
        (``sidewalk`` width beside them) and dashed lane-edge markings of every lane."""
        roads = list(getattr(world, "roads", []))
        return GroundTexture.from_lanes(world.lanes, (), res=res, seed=seed, roads=roads)

    @staticmethod
    def from_lanes(
        lanes: Sequence[object],
        sidewalks: Sequence[np.ndarray] = (),
        res: float = 0.1,
        seed: int = 0,
        roads: Sequence[object] = (),
        style: GroundStyle | None = None,
    ) -> GroundTexture:
        """Rasterise lanes (objects with ``centerline`` (M, 2) m and ``width`` m), sidewalk
        polylines and roads (``centerline``, ``half_width`` m, optional ``sidewalk`` m and
        ``closed``) at ``res`` m/px; ``style``: margin and marking sizes (:class:`GroundStyle`).

        Lane boundaries get dashed markings (``style.dash`` = (on, off) m).
        """
        style = style or GroundStyle()
        pts = [np.asarray(ln.centerline, float) for ln in lanes] + [
            np.asarray(s, float) for s in sidewalks
        ]
        pts += [np.asarray(r.centerline, float) for r in roads]
        if not pts:
            return GroundTexture.plain()
        allp = np.concatenate(pts)
        canvas = _Canvas(allp.min(0) - style.margin, allp.max(0) + style.margin, res)
        for rd in roads:  # sidewalk band first, then the drivable surface over it
            hw, sw = float(rd.half_width), float(getattr(rd, "sidewalk", 0.0))
            if sw > 0:
                canvas.line(rd.centerline, bool(getattr(rd, "closed", False)), 3, 2 * (hw + sw))
        for rd in roads:
            closed = bool(getattr(rd, "closed", False))
            canvas.line(rd.centerline, closed, 1, 2 * float(rd.half_width))
        for s in sidewalks:
            if len(s) >= 2:
                canvas.line(s, False, 3, style.sidewalk_width)
        lines = [np.asarray(ln.centerline, float) for ln in lanes]
        for ln, cl in zip(lanes, lines):
            if len(cl) >= 2:
                canvas.line(cl, False, 1, float(ln.width))
        for ln, cl in zip(lanes, lines):
            if len(cl) < 2:
                continue
            for side in (-1.0, 1.0):
                edge = _offset_polyline(cl, side * float(ln.width) / 2.0)
                for seg in _dash_polyline(edge, *style.dash):
                    canvas.line(seg, False, 2, style.marking_width)
        return GroundTexture(canvas.raster, canvas.lo, res, seed)

    def sample(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Colour (P, 3) in [0, 1] at world points (x, y) (m)."""
        c = np.floor((x - self.origin[0]) / self.res).astype(np.int64)
        r = np.floor((y - self.origin[1]) / self.res).astype(np.int64)
        inside = (r >= 0) & (r < self.raster.shape[0]) & (c >= 0) & (c < self.raster.shape[1])
        t = np.zeros(len(x), np.int64)
        t[inside] = self.raster[r[inside], c[inside]]
        tex = value_noise(x, y, self.seed + t, (0.06, 0.2, 0.8), (0.45, 0.35, 0.2))
        amp = np.array([0.9, 0.8, 0.25, 0.5])[t]
        return np.clip(self._COL[t] * (1.0 - amp / 2 + amp * tex)[:, None], 0, 1)


def _offset_polyline(p: np.ndarray, off: float) -> np.ndarray:
    """Polyline shifted ``off`` m to its left (positive) along the per-vertex normal."""
    t = np.gradient(p, axis=0)
    t /= np.maximum(np.linalg.norm(t, axis=1, keepdims=True), 1e-9)
    return p + off * np.stack([-t[:, 1], t[:, 0]], 1)


def _dash_polyline(p: np.ndarray, on: float, off: float) -> list[np.ndarray]:
    """Cut a polyline into dashes of ``on`` m separated by ``off`` m (resampled at 0.5 m)."""
    seg = np.linalg.norm(np.diff(p, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    if s[-1] <= 0:
        return []
    ss = np.arange(0.0, s[-1], 0.5)
    q = np.stack([np.interp(ss, s, p[:, 0]), np.interp(ss, s, p[:, 1])], 1)
    dash_id = np.floor(ss / (on + off)).astype(np.int64)
    keep = (ss - dash_id * (on + off)) < on
    return [
        q[keep & (dash_id == k)]
        for k in np.unique(dash_id[keep])
        if np.sum(keep & (dash_id == k)) >= 2
    ]
