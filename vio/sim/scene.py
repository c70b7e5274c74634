"""A textured room made of axis-aligned boxes, with fast vectorised ray casting.

Box 0 is the room, seen from inside; the others (crates, pillars) are seen from outside. Axis-aligned boxes
keep ray casting cheap: one reciprocal per ray direction component serves every box (slab method). Each
box face gets a texture patch in one atlas image, so shading a whole image is a single `cv2.remap`. The
atlas also has a 4x smaller level, blended in where a pixel covers several texels, against aliasing.

Textures are multi-scale noise plus random rectangles, discs and lines (corners and edges for feature
detectors); `plain_fraction` paints large uniform patches (low-texture areas, hard for trackers).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from vio import VioError

# Face axes: a face normal to axis k is parameterised by the other two world axes (u, v).
_UV_AXES = ((1, 2), (0, 2), (0, 1))
_PAD = 2  # texels of border around each face patch in the atlas (bilinear lookups must not bleed)
MIP_FACTOR = 4  # size ratio between atlas level 0 and level 1


@dataclass(frozen=True)
class Box:
    """Axis-aligned box [lo, hi] in world metres. `interior` marks the room (rays hit it from inside)."""

    lo: tuple[float, float, float]
    hi: tuple[float, float, float]
    interior: bool = False


@dataclass(frozen=True)
class Face:
    box: int
    axis: int  # normal axis
    side: int  # 0: the lo plane of the box, 1: the hi plane
    u_range: tuple[float, float]
    v_range: tuple[float, float]
    hidden: bool  # lies on the room's boundary (a crate's bottom on the floor): never visible

    @property
    def area(self) -> float:
        return (self.u_range[1] - self.u_range[0]) * (self.v_range[1] - self.v_range[0])


def _faces(boxes: list[Box]) -> list[Face]:
    room = boxes[0]
    out = []
    for b, box in enumerate(boxes):
        for k in range(3):
            u, v = _UV_AXES[k]
            for side in (0, 1):
                plane = (box.lo, box.hi)[side][k]
                hidden = b > 0 and plane in (room.lo[k], room.hi[k])
                out.append(Face(b, k, side, (box.lo[u], box.hi[u]), (box.lo[v], box.hi[v]), hidden))
    return out


def face_texture(rng: np.random.Generator, w: int, h: int, ppm: float, plain_fraction: float = 0.0) -> np.ndarray:
    """A w x h float32 texture in [0, 1]: noise at scales 2 m .. 2 cm, random shapes, optional plain patches.

    Scales are given in metres (times `ppm`, texels per metre) so that every face has the same look."""
    tex = np.zeros((h, w), np.float32)
    for scale_m, weight in ((2.0, 0.35), (0.6, 0.3), (0.2, 0.25), (0.06, 0.2), (0.02, 0.12)):
        cell = scale_m * ppm
        if cell < 1.5:
            continue
        gh, gw = int(h / cell) + 3, int(w / cell) + 3
        noise = rng.standard_normal((gh, gw)).astype(np.float32)
        big = cv2.resize(noise, (int(gw * cell), int(gh * cell)), interpolation=cv2.INTER_CUBIC)
        tex += weight * big[:h, :w]
    area = w * h / ppm**2
    shapes = np.zeros((h, w), np.float32)  # added to the noise, so shapes keep some texture inside
    for _ in range(int(12 * area) + 2):  # ~12 shapes per square metre
        size = rng.uniform(0.03, 0.5) * ppm
        x, y = rng.uniform(0, w), rng.uniform(0, h)
        val = float(rng.choice([-1.0, 1.0]) * rng.uniform(0.4, 1.2))
        kind = rng.integers(3)
        if kind == 0:
            p1 = (int(x), int(y))
            p2 = (int(x + size * rng.uniform(0.3, 1.5)), int(y + size * rng.uniform(0.3, 1.5)))
            cv2.rectangle(shapes, p1, p2, val, -1)
        elif kind == 1:
            cv2.circle(shapes, (int(x), int(y)), max(1, int(size / 2)), val, -1)
        else:
            a = rng.uniform(0, np.pi)
            p2 = (int(x + size * np.cos(a)), int(y + size * np.sin(a)))
            cv2.line(shapes, (int(x), int(y)), p2, val, max(1, int(0.01 * ppm)))
    tex = 0.5 + 0.2 * (tex + shapes)
    remaining = plain_fraction * w * h
    while remaining > 0.02 * w * h:  # large uniform patches, 1..3 m, nearly featureless
        pw = min(w, int(rng.uniform(1.0, 3.0) * ppm))
        ph = min(h, int(rng.uniform(1.0, 3.0) * ppm))
        x0, y0 = int(rng.integers(0, max(1, w - pw + 1))), int(rng.integers(0, max(1, h - ph + 1)))
        level = rng.uniform(0.35, 0.75)
        ramp = np.linspace(0, rng.uniform(-0.04, 0.04), pw, dtype=np.float32)  # faint shading gradient
        tex[y0:y0 + ph, x0:x0 + pw] = level + ramp[None, :]
        remaining -= pw * ph
    return np.clip(tex, 0.03, 0.97)


class Scene:
    """Boxes + texture atlas. Build with `default_scene`; ray cast with `cast`; sample with `sample_points`."""

    def __init__(self, boxes: list[Box], ppm: float = 200.0, seed: int = 0, plain_fraction: float = 0.0,
                 aliasing_period_m: float | None = None, brightness: float = 1.0,
                 texture_copies: dict[int, int] | None = None):
        if not boxes or not boxes[0].interior:
            raise VioError("scene: the first box must be the room (interior=True)")
        self.boxes = boxes
        self.ppm = float(ppm)
        self.faces = _faces(boxes)
        self.lo = np.array([b.lo for b in boxes], dtype=float)
        self.hi = np.array([b.hi for b in boxes], dtype=float)
        # repeated walls: the room's faces repeat their texture every aliasing_period_m (identical shelves)
        self.aliasing_period_m = aliasing_period_m
        self.brightness = float(brightness)  # < 1: a dim place (less contrast, the pixel noise counts more)
        # box -> an earlier box of the same size whose face textures it repeats (identical shelf units)
        self.texture_copies = dict(texture_copies or {})
        for b, src in self.texture_copies.items():
            if not (0 < src < b < len(boxes)) or not np.allclose(np.subtract(boxes[b].hi, boxes[b].lo),
                                                                 np.subtract(boxes[src].hi, boxes[src].lo)):
                raise VioError(f"scene: box {b} cannot copy the textures of box {src} (an earlier box of its size)")
        self._build_atlas(np.random.default_rng([seed, 5150]), plain_fraction)

    # -- textures --------------------------------------------------------------------------------------
    def _build_atlas(self, rng: np.random.Generator, plain_fraction: float) -> None:
        """Shelf-pack one texture patch per face into an atlas; store per-face lookup constants."""
        sizes = [(max(2, int(np.ceil((f.u_range[1] - f.u_range[0]) * self.ppm))) + 2 * _PAD,
                  max(2, int(np.ceil((f.v_range[1] - f.v_range[0]) * self.ppm))) + 2 * _PAD) for f in self.faces]
        width = max(s[0] for s in sizes)
        order = sorted(range(len(sizes)), key=lambda i: -sizes[i][1])
        offsets = [(0, 0)] * len(sizes)
        x = y = row_h = 0
        for i in order:
            w, h = sizes[i]
            if x + w > width:
                x, y, row_h = 0, y + row_h, 0
            offsets[i] = (x, y)
            x, row_h = x + w, max(row_h, h)
        height = y + row_h
        height += (-height) % MIP_FACTOR
        width += (-width) % MIP_FACTOR
        if max(width, height) >= 32767:
            raise VioError(f"scene texture atlas {width}x{height} too large for cv2.remap; lower ppm")
        atlas = np.full((height, width), 0.5, np.float32)
        n = len(self.faces)
        if n > 127:
            raise VioError(f"scene: {len(self.boxes)} boxes; at most 21 fit the int8 face index")
        self.face_axis = np.zeros(n, np.int8)
        self.face_cx = np.zeros(n, np.float32)  # atlas x = p_u * ppm + face_cx
        self.face_cy = np.zeros(n, np.float32)
        patches: dict[tuple[int, int, int], np.ndarray] = {}
        for i, f in enumerate(self.faces):
            w, h = sizes[i]
            ox, oy = offsets[i]
            src = self.texture_copies.get(f.box)
            if not f.hidden and src is not None:  # (sizes may differ by a texel of round-off: the padding)
                p = patches[(src, f.axis, f.side)]
                hh, ww = min(h, p.shape[0]), min(w, p.shape[1])
                atlas[oy:oy + hh, ox:ox + ww] = p[:hh, :ww]
            elif not f.hidden:
                # a per-face brightness stands in for lighting; plain patches mostly on the room itself
                plain = plain_fraction if f.box == 0 else plain_fraction / 3
                period = self.aliasing_period_m
                if f.box == 0 and period:
                    n = max(8, int(round(period * self.ppm)))
                    tw, th = min(w, n), min(h, n)
                    # no plain patches in the tile: at 1-3 m one would cover a whole period, and the repeated
                    # walls would come out plain (nothing to alias; realistic flights rejected 40 % of their frames)
                    tile = face_texture(rng, tw, th, self.ppm, 0.0)
                    patch = np.tile(tile, (int(np.ceil(h / th)), int(np.ceil(w / tw))))[:h, :w]
                else:
                    patch = face_texture(rng, w, h, self.ppm, plain)
                patches[(f.box, f.axis, f.side)] = patch * rng.uniform(0.7, 1.15)
                atlas[oy:oy + h, ox:ox + w] = patches[(f.box, f.axis, f.side)]
            self.face_axis[i] = f.axis
            self.face_cx[i] = ox + _PAD - f.u_range[0] * self.ppm
            self.face_cy[i] = oy + _PAD - f.v_range[0] * self.ppm
        atlas = np.clip(atlas * (255.0 * self.brightness), 0, 255)
        self.atlas = atlas.astype(np.float32)
        self.atlas_small = cv2.resize(cv2.GaussianBlur(self.atlas, (0, 0), MIP_FACTOR / 2.5),
                                      (width // MIP_FACTOR, height // MIP_FACTOR), interpolation=cv2.INTER_AREA)

    # -- geometry --------------------------------------------------------------------------------------
    def cast(self, origin: np.ndarray, d: tuple[np.ndarray, np.ndarray, np.ndarray],
             windows: list | None = None) -> tuple[np.ndarray, np.ndarray]:
        """First hit of rays origin + t * d. `d` is three arrays (x, y, z components) of any equal shape;
        returns t (same shape; not normalised: t is in units of |d|) and the face index hit.

        `windows` optionally gives, per box after the room, an index (e.g. slices) of the rays that can hit
        it, or None for "cannot be seen" (the renderer culls boxes by their image footprint)."""
        o = np.asarray(origin, dtype=float)
        dt = d[0].dtype if np.issubdtype(d[0].dtype, np.floating) else np.float64
        with np.errstate(divide="ignore", invalid="ignore"):
            # a tiny offset keeps exact zeros (and -0.0) from making -inf/nan hits
            inv = [(1.0 / (np.asarray(c, dtype=dt) + dt.type(1e-30))) for c in d]
            # the room, from inside: on each axis the plane ahead is the one at positive distance
            tk = [np.maximum(dt.type(self.lo[0, k] - o[k]) * inv[k], dt.type(self.hi[0, k] - o[k]) * inv[k])
                  for k in range(3)]
            t = np.minimum(np.minimum(tk[0], tk[1]), tk[2])
            e0, e1 = tk[0] == t, tk[1] == t  # int8/bool arithmetic: a quarter of the memory traffic
            axis = np.where(e0, np.int8(0), np.where(e1, np.int8(1), np.int8(2)))
            face = axis * np.int8(2) + np.where(e0, d[0] > 0, np.where(e1, d[1] > 0, d[2] > 0))
            for b in range(1, len(self.boxes)):
                win = (...,) if windows is None else windows[b - 1]
                if win is None:
                    continue
                tmin, tmax = [], []
                for k in range(3):
                    ik = inv[k][win]
                    t1 = dt.type(self.lo[b, k] - o[k]) * ik
                    t2 = dt.type(self.hi[b, k] - o[k]) * ik
                    tmin.append(np.minimum(t1, t2))
                    tmax.append(np.maximum(t1, t2))
                tfar = np.minimum(np.minimum(tmax[0], tmax[1]), tmax[2])
                tnear = np.maximum(np.maximum(tmin[0], tmin[1]), tmin[2])
                hit = (tnear <= tfar) & (tnear > 0) & (tnear < t[win])
                if not hit.any():
                    continue
                axis = np.where((tmin[0] >= tmin[1]) & (tmin[0] >= tmin[2]), 0, np.where(tmin[1] >= tmin[2], 1, 2))
                dk = np.where(axis == 0, d[0][win], np.where(axis == 1, d[1][win], d[2][win]))
                fid = (6 * b + 2 * axis + (dk < 0)).astype(np.int8)  # moving -k enters through the hi plane
                t[win] = np.where(hit, tnear, t[win])
                face[win] = np.where(hit, fid, face[win])
        return t, face

    def texture_coords(self, origin: np.ndarray, d: tuple[np.ndarray, np.ndarray, np.ndarray], t: np.ndarray,
                       face: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Atlas pixel coordinates (map_x, map_y) of the hit points, for cv2.remap."""
        o = np.asarray(origin, dtype=float)
        ft = t.dtype.type
        # hit point p = o + t d; the origin's share goes into per-face constants (cheap: one per face)
        u_axis = np.where(self.face_axis == 0, 1, 0)
        v_axis = np.where(self.face_axis == 2, 1, 2)
        cx = (self.face_cx + self.ppm * o[u_axis]).astype(t.dtype)
        cy = (self.face_cy + self.ppm * o[v_axis]).astype(t.dtype)
        axis = self.face_axis[face]
        du = np.where(axis == 0, d[1], d[0])
        dv = np.where(axis == 2, d[1], d[2])
        ppm = ft(self.ppm)
        return (t * ppm) * du + cx[face], (t * ppm) * dv + cy[face]

    def contains(self, p: np.ndarray, margin: float = 0.0) -> np.ndarray:
        """True for points (N, 3) inside the room and outside every box, by at least `margin` metres."""
        p = np.atleast_2d(p)
        ok = np.all((p > self.lo[0] + margin) & (p < self.hi[0] - margin), axis=1)
        for b in range(1, len(self.boxes)):
            ok &= ~np.all((p > self.lo[b] - margin) & (p < self.hi[b] + margin), axis=1)
        return ok

    def sample_points(self, n: int, rng: np.random.Generator) -> np.ndarray:
        """n points (n, 3) uniformly distributed over the visible surfaces (landmarks for tests).

        Points on the room's walls that lie under or inside a crate are redrawn."""
        faces = [f for f in self.faces if not f.hidden]
        area = np.array([f.area for f in faces])
        out = np.zeros((0, 3))
        while len(out) < n:
            m = 2 * (n - len(out)) + 8
            idx = rng.choice(len(faces), size=m, p=area / area.sum())
            pts = np.zeros((m, 3))
            for j, i in enumerate(idx):
                f = faces[i]
                u, v = _UV_AXES[f.axis]
                pts[j, f.axis] = (self.lo, self.hi)[f.side][f.box, f.axis]
                pts[j, u] = rng.uniform(*f.u_range)
                pts[j, v] = rng.uniform(*f.v_range)
            covered = np.zeros(m, bool)
            for b in range(1, len(self.boxes)):  # on a room wall but inside/under a box
                covered |= np.all((pts >= self.lo[b] - 1e-9) & (pts <= self.hi[b] + 1e-9), axis=1) & \
                    np.array([faces[i].box != b for i in idx])
            out = np.vstack([out, pts[~covered]])
        return out[:n]


def default_scene(seed: int = 0, ppm: float = 200.0, plain_fraction: float = 0.0,
                  aliasing_period_m: float | None = None) -> Scene:
    """A 10 m x 8 m x 4 m room (x in [-5, 5], y in [-4, 4], z in [0, 4]) with crates and pillars along the
    walls (outside motion.FLIGHT_BOX by >= 1 m) and two low crates on the floor below the flight area."""
    boxes = [
        Box((-5.0, -4.0, 0.0), (5.0, 4.0, 4.0), interior=True),
        Box((3.7, -3.6, 0.0), (4.6, -2.2, 1.2)),  # crates along the walls
        Box((-4.7, 1.0, 0.0), (-3.7, 2.6, 0.8)),
        Box((-1.0, 2.9, 0.0), (1.4, 3.8, 1.5)),
        Box((-2.5, -3.8, 0.0), (-1.2, -2.9, 2.2)),
        Box((3.9, 1.5, 0.0), (4.4, 2.0, 4.0)),  # pillars
        Box((-4.3, -3.5, 0.0), (-3.8, -3.0, 4.0)),
        Box((0.6, -0.9, 0.0), (1.4, -0.2, 0.25)),  # low crates under the flight area
        Box((-1.6, 0.4, 0.0), (-0.9, 1.2, 0.1)),
    ]
    return Scene(boxes, ppm=ppm, seed=seed, plain_fraction=plain_fraction, aliasing_period_m=aliasing_period_m)


def shelves_scene(seed: int = 0, ppm: float = 200.0, plain_fraction: float = 0.0) -> Scene:
    """The room with eight identical shelf units (1.6 m x 0.7 m x 2.2 m, the same textures) along its two long
    walls every 2.4 m, and the walls, floor and ceiling repeating their texture every 2.4 m too: places 2.4 m
    apart look the same but are not (the aliasing a warehouse aisle makes). The loop stage must refuse them."""
    period, width, xs = 2.4, 1.6, (-4.4, -2.0, 0.4, 2.8)
    boxes = [Box((-5.0, -4.0, 0.0), (5.0, 4.0, 4.0), interior=True)]
    for y0, y1 in ((3.1, 3.8), (-3.8, -3.1)):
        boxes += [Box((x, y0, 0.0), (x + width, y1, 2.2)) for x in xs]
    return Scene(boxes, ppm=ppm, seed=seed, plain_fraction=plain_fraction, aliasing_period_m=period,
                 texture_copies={b: 1 for b in range(2, len(boxes))})


SCENES = ("room", "hall", "shelves")
ALIASING_ROOM_ONLY = "simulate: --aliasing is for the room scene only (the shelves scene repeats by itself)"
HALL_MAX_PPM = 50.0  # the hall's 1700 m^2 of surface at 200 texels/m would not fit one cv2.remap atlas
HALL_BRIGHTNESS = 0.4


def hall_scene(seed: int = 0, ppm: float = 200.0, plain_fraction: float = 0.0) -> Scene:
    """A large dim machine hall: 25 m x 20 m x 8 m (x in [-12.5, 12.5], y in [-10, 10], z in [0, 8]),
    the flight area (motion.FLIGHT_BOX) in its middle, so the walls are 10-15 m away (stereo disparity
    3-5 px) and most texture is far: what the back end's depth limit and far landmarks are tested on.
    Pillars and machines stand well outside the flight area. Textures are at most HALL_MAX_PPM texels/m
    (a pixel at 10 m covers 2 cm) and the whole hall at HALL_BRIGHTNESS of the room's brightness."""
    boxes = [
        Box((-12.5, -10.0, 0.0), (12.5, 10.0, 8.0), interior=True),
        Box((-6.3, -5.3, 0.0), (-5.7, -4.7, 8.0)),  # pillars
        Box((5.7, -5.3, 0.0), (6.3, -4.7, 8.0)),
        Box((-6.3, 4.7, 0.0), (-5.7, 5.3, 8.0)),
        Box((5.7, 4.7, 0.0), (6.3, 5.3, 8.0)),
        Box((8.0, -8.5, 0.0), (11.5, -5.5, 3.0)),  # machines and shelves along the walls
        Box((-11.5, 6.0, 0.0), (-8.0, 9.0, 2.5)),
        Box((-3.0, 8.5, 0.0), (4.0, 9.6, 4.5)),
        Box((-10.0, -9.6, 0.0), (-4.0, -8.4, 4.0)),
        Box((10.8, 1.0, 0.0), (12.0, 4.5, 5.0)),
        Box((1.0, -4.5, 0.0), (2.5, -3.5, 0.8)),  # low crates beside the flight area
        Box((-3.5, 3.2, 0.0), (-2.0, 4.2, 0.6)),
    ]
    return Scene(boxes, ppm=min(ppm, HALL_MAX_PPM), seed=seed, plain_fraction=plain_fraction,
                 brightness=HALL_BRIGHTNESS)


def make_scene(name: str, seed: int = 0, ppm: float = 200.0, plain_fraction: float = 0.0,
               aliasing_period_m: float | None = None) -> Scene:
    """The scene called `name` (one of SCENES): the default room or the hall."""
    if name == "room":
        return default_scene(seed, ppm, plain_fraction, aliasing_period_m)
    if name in ("hall", "shelves") and aliasing_period_m:
        raise VioError(ALIASING_ROOM_ONLY)
    if name == "hall":
        return hall_scene(seed, ppm, plain_fraction)
    if name == "shelves":
        return shelves_scene(seed, ppm, plain_fraction)
    raise VioError(f"simulate: unknown scene {name!r}; expected one of {list(SCENES)}")
