"""Articulated synthetic creatures: tapered capsules on a kinematic tree.

A creature is a rigid *body* (a few tapered capsules) carrying *limbs*. Each
limb is a chain of tapered capsules ("round cones": the convex hull of two
spheres) hanging from a junction point on the body. At time ``t`` every joint
angle is a smooth periodic function of ``t``; the body itself translates and
rotates a little. :meth:`Creature.pose` evaluates the tree into a
:class:`Pose`: the capsules in world coordinates (mm, z up, floor z = 0) plus
the ground truth the spine pipeline is scored against: each limb's *tip* (the
extreme surface point at the limb's end) and *axis* (polyline from the junction
on the body to the tip).

Subjects (``make_creature(name)``):

``starfish``
    Five curling arms around a flat central disc lying just above the floor
    (the synthetic starfish of Brostow et al. 2004, Fig. 2). Limbs ``arm0..arm4``.
``quadruped``
    Torso, four walking legs, a neck with head and a wagging tail: six limb tips
    ``leg_fl, leg_fr, leg_hl, leg_hr, head, tail``.
``tailed_quadruped``
    The quadruped with a 144 mm tail tapering from 36 mm to 16 mm thick at every scale
    (``scale`` grows the animal, not its tail): a thin limb that a coarse grid loses and
    a grid following the cameras keeps.
``biped``
    Upright torso with head, two swinging arms and two walking legs:
    ``head, arm_l, arm_r, leg_l, leg_r``.

Hard cases (optional, for the spine tests): ``tuck=(t0, t1)`` presses two limbs
together (the creature's :attr:`Creature.tuck_pair`) during ``t0 <= t < t1``
(smooth 0.1 s transitions outside the interval), so their silhouettes merge;
``spur=(t0, t1)`` grows a short spurious protrusion out of the body during
``t0 <= t < t1`` (give an interval of one frame period for a one-frame
protrusion). The protrusion is labelled as body (limb label -1) and has no tip.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

__all__ = ["CREATURES", "BODY", "LimbSpec", "Creature", "Pose", "make_creature", "round_cone_sdf", "round_cone_sdf_pairs"]

CREATURES = ("starfish", "quadruped", "biped", "tailed_quadruped")
BODY = -1  # limb label of body capsules


def _rot(axis: np.ndarray, angle: float) -> np.ndarray:
    a = np.asarray(axis, dtype=np.float64)
    a = a / np.linalg.norm(a)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + math.sin(angle) * K + (1 - math.cos(angle)) * (K @ K)


def _unit(v) -> np.ndarray:
    v = np.asarray(v, dtype=np.float64)
    return v / np.linalg.norm(v)


def _align(a, b) -> np.ndarray:
    """The smallest rotation taking direction ``a`` to direction ``b``."""
    a, b = _unit(a), _unit(b)
    c = np.cross(a, b)
    s = float(np.linalg.norm(c))
    if s < 1e-12:
        return np.eye(3) if a @ b > 0 else _rot(np.cross(a, [1.0, 0, 0]) if abs(a[0]) < 0.9 else np.cross(a, [0, 1.0, 0]), math.pi)
    return _rot(c, math.atan2(s, float(a @ b)))


def round_cone_sdf_pairs(points: np.ndarray, p0: np.ndarray, p1: np.ndarray, r0: np.ndarray, r1: np.ndarray) -> np.ndarray:
    """Exact signed distance of points to round cones, broadcasting pairwise.

    After I. Quilez's ``sdRoundCone``; a cone whose one sphere contains the
    other degenerates to the larger sphere. Works in any dimension >= 2 (the
    last axis holds the coordinates): in 2-D it is the distance to the convex
    hull of two discs.

    Parameters
    ----------
    points : (..., D) float ndarray
    p0, p1 : (..., D) float ndarray
        Sphere centres (broadcast against ``points``).
    r0, r1 : (...) float ndarray
        Sphere radii.

    Returns
    -------
    (...) float ndarray
        Signed distance (negative inside).
    """
    P = np.asarray(points, dtype=np.float64)
    a = np.asarray(p0, dtype=np.float64)
    ba = np.asarray(p1, dtype=np.float64) - a
    r0 = np.asarray(r0, dtype=np.float64)
    r1 = np.asarray(r1, dtype=np.float64)
    l2 = (ba * ba).sum(-1)
    rr = r0 - r1
    a2 = l2 - rr * rr
    degenerate = a2 <= 1e-9 * np.maximum(l2, 1e-300) + 1e-12
    l2s = np.where(degenerate, 1.0, l2)
    a2s = np.where(degenerate, 1.0, a2)
    il2 = 1.0 / l2s
    pa = P - a
    y = (pa * ba).sum(-1)
    z = y - l2s
    q = pa * l2s[..., None] - ba * y[..., None]
    x2 = (q * q).sum(-1)
    y2 = y * y * l2s
    z2 = z * z * l2s
    k = np.sign(rr) * rr * rr * x2
    d_end1 = np.sqrt(x2 + z2) * il2 - r1
    d_end0 = np.sqrt(x2 + y2) * il2 - r0
    d_side = (np.sqrt(x2 * a2s * il2) + y * rr) * il2 - r0
    out = np.where(np.sign(z) * a2s * z2 > k, d_end1, np.where(np.sign(y) * a2s * y2 < k, d_end0, d_side))
    if np.any(degenerate):
        s0 = np.sqrt((pa * pa).sum(-1)) - r0
        pb = pa - ba
        s1 = np.sqrt((pb * pb).sum(-1)) - r1
        out = np.where(degenerate, np.minimum(s0, s1), out)
    return out


def round_cone_sdf(points: np.ndarray, p0: np.ndarray, p1: np.ndarray, r0: np.ndarray, r1: np.ndarray) -> np.ndarray:
    """Exact signed distance from every point to every round cone.

    Parameters
    ----------
    points : (N, 3) float ndarray
    p0, p1 : (M, 3) float ndarray
        Sphere centres of each cone.
    r0, r1 : (M,) float ndarray
        Sphere radii.

    Returns
    -------
    (N, M) float ndarray
        Signed distance of every point to every cone (negative inside).
    """
    P = np.asarray(points, dtype=np.float64)[:, None, :]
    return round_cone_sdf_pairs(
        P,
        np.asarray(p0, dtype=np.float64)[None],
        np.asarray(p1, dtype=np.float64)[None],
        np.asarray(r0, dtype=np.float64)[None],
        np.asarray(r1, dtype=np.float64)[None],
    )


@dataclass(frozen=True, eq=False)
class Pose:
    """A creature at one instant: tapered capsules and limb ground truth.

    Parameters
    ----------
    p0, p1 : (M, 3) float ndarray
        Sphere centres of the capsules (mm, world frame).
    r0, r1 : (M,) float ndarray
        Radii at ``p0`` and ``p1`` (mm).
    limb : (M,) int ndarray
        Limb label of every capsule: index into ``names``, or -1 for the body.
    names : tuple of str
        Limb ids, in label order.
    tips : dict str -> (3,) float ndarray
        Extreme surface point at the end of every limb.
    axes : dict str -> (K, 3) float ndarray
        Limb axis polyline from the junction on the body to the tip.
    time : float
        Time of the pose, seconds.
    rest : (M, 3, 4) float ndarray, optional
        Per capsule, the rigid motion ``[R | t]`` that takes its rest position to this pose.
        When given, the renderer attaches the surface texture to the body (evaluated at the
        rest position of every surface point, so it moves with the part, twist included);
        without it the texture is a function of the world position.
    """

    p0: np.ndarray
    p1: np.ndarray
    r0: np.ndarray
    r1: np.ndarray
    limb: np.ndarray
    names: tuple[str, ...] = ()
    tips: dict = field(default_factory=dict)
    axes: dict = field(default_factory=dict)
    time: float = 0.0
    rest: np.ndarray | None = None

    def __post_init__(self) -> None:
        p0 = np.asarray(self.p0, dtype=np.float64).reshape(-1, 3)
        p1 = np.asarray(self.p1, dtype=np.float64).reshape(-1, 3)
        r0 = np.asarray(self.r0, dtype=np.float64).reshape(-1)
        r1 = np.asarray(self.r1, dtype=np.float64).reshape(-1)
        limb = np.asarray(self.limb, dtype=np.int64).reshape(-1)
        m = p0.shape[0]
        if not (p1.shape[0] == r0.shape[0] == r1.shape[0] == limb.shape[0] == m) or m == 0:
            raise ValueError("p0, p1, r0, r1 and limb must describe the same non-zero number of capsules")
        if np.any(r0 <= 0) or np.any(r1 <= 0):
            raise ValueError("r0, r1: capsule radii must be positive")
        for name, v in (("p0", p0), ("p1", p1), ("r0", r0), ("r1", r1), ("limb", limb)):
            object.__setattr__(self, name, v)
        if self.rest is not None:
            rest = np.asarray(self.rest, dtype=np.float64)
            if rest.shape != (m, 3, 4):
                raise ValueError(f"rest must have shape ({m}, 3, 4), got {rest.shape}")
            object.__setattr__(self, "rest", rest)

    @classmethod
    def spheres(cls, centers: np.ndarray, radii: np.ndarray) -> "Pose":
        """A pose made of plain spheres (each its own degenerate capsule, label -1)."""
        c = np.asarray(centers, dtype=np.float64).reshape(-1, 3)
        r = np.broadcast_to(np.asarray(radii, dtype=np.float64), (c.shape[0],)).copy()
        return cls(p0=c, p1=c.copy(), r0=r, r1=r.copy(), limb=np.full(c.shape[0], BODY))

    @property
    def n_capsules(self) -> int:
        return int(self.p0.shape[0])

    def bounding_sphere(self) -> tuple[np.ndarray, float]:
        """Centre (3,) and radius of a sphere enclosing every capsule."""
        lo, hi = self.bounds()
        c = (lo + hi) / 2
        r = np.maximum(np.linalg.norm(self.p0 - c, axis=1) + self.r0, np.linalg.norm(self.p1 - c, axis=1) + self.r1)
        return c, float(r.max())

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Axis-aligned bounds (lo (3,), hi (3,)) of the surface."""
        lo = np.minimum((self.p0 - self.r0[:, None]).min(0), (self.p1 - self.r1[:, None]).min(0))
        hi = np.maximum((self.p0 + self.r0[:, None]).max(0), (self.p1 + self.r1[:, None]).max(0))
        return lo, hi

    def capsule_sdf(self, points: np.ndarray) -> np.ndarray:
        """(N, M) signed distance of every point to every capsule."""
        pts = np.asarray(points, dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1] != 3:
            raise ValueError(f"points must have shape (N, 3), got {pts.shape}")
        return round_cone_sdf(pts, self.p0, self.p1, self.r0, self.r1)

    def sdf(self, points: np.ndarray, *, chunk: int = 65536) -> np.ndarray:
        """Signed distance (mm) of points to the creature's surface, negative inside.

        Parameters
        ----------
        points : (N, 3) float ndarray

        Returns
        -------
        (N,) float ndarray
            ``min`` over the capsules of the exact round-cone distance.
        """
        pts = np.asarray(points, dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1] != 3:
            raise ValueError(f"points must have shape (N, 3), got {pts.shape}")
        out = np.empty(pts.shape[0])
        for s in range(0, pts.shape[0], chunk):
            out[s : s + chunk] = self.capsule_sdf(pts[s : s + chunk]).min(axis=1)
        return out

    def grid_sdf(self, axes, *, coarse: int = 4) -> np.ndarray:
        """:meth:`sdf` on the grid of ``axes`` for marching cubes: exact near the surface, the
        right sign elsewhere, at a fraction of the cost of every grid point.

        The distance is evaluated on every ``coarse``-th point along each axis, then exactly at
        the grid points whose nearest coarse sample is within 2 grid steps plus its own distance
        of the surface; every other point takes its coarse sample's value. The distance is
        1-Lipschitz, so those points keep the right sign, and every corner of a grid cell the
        surface crosses (within sqrt(3) steps of it) is exact: marching cubes gives the mesh of
        :meth:`sdf` on every point.

        Parameters
        ----------
        axes : sequence of 3 (n_k,) float ndarray
            The grid's coordinates along x, y and z (mm), each with one step (the largest is used).
        coarse : int, optional
            The coarse grid's step, in grid steps.

        Returns
        -------
        (n_x, n_y, n_z) float ndarray
        """
        axes = [np.asarray(a, dtype=np.float64) for a in axes]
        if len(axes) != 3 or any(a.ndim != 1 or len(a) == 0 for a in axes):
            raise ValueError("axes must be 3 non-empty 1-D arrays")
        if int(coarse) < 1:
            raise ValueError(f"coarse must be >= 1, got {coarse!r}")
        k = int(coarse)
        h = max((float(np.diff(a).max()) for a in axes if len(a) > 1), default=0.0)
        near = [np.minimum(np.rint(np.arange(len(a)) / k).astype(int), (len(a) - 1) // k) for a in axes]
        sub = [a[::k] for a in axes]
        grid = np.stack(np.meshgrid(*sub, indexing="ij"), axis=-1).reshape(-1, 3)
        values = self.sdf(grid).reshape([len(a) for a in sub])[np.ix_(*near)]
        off = [np.abs(a - s[i]) ** 2 for a, s, i in zip(axes, sub, near)]
        reach = np.sqrt(off[0][:, None, None] + off[1][None, :, None] + off[2][None, None, :]) + 2.0 * h
        exact = np.nonzero(np.abs(values) <= reach)
        values[exact] = self.sdf(np.stack([a[i] for a, i in zip(axes, exact)], axis=1))
        return values

    def label_at(self, points: np.ndarray, *, chunk: int = 65536) -> np.ndarray:
        """Limb label (-1 = body) of the capsule nearest to every point.

        Parameters
        ----------
        points : (N, 3) float ndarray

        Returns
        -------
        (N,) int ndarray
        """
        pts = np.asarray(points, dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1] != 3:
            raise ValueError(f"points must have shape (N, 3), got {pts.shape}")
        out = np.empty(pts.shape[0], dtype=np.int64)
        for s in range(0, pts.shape[0], chunk):
            out[s : s + chunk] = self.limb[self.capsule_sdf(pts[s : s + chunk]).argmin(axis=1)]
        return out

    def tip_array(self) -> np.ndarray:
        """(L, 3) tips in ``names`` order."""
        return np.stack([self.tips[n] for n in self.names]) if self.names else np.zeros((0, 3))


@dataclass(frozen=True)
class LimbSpec:
    """One limb: a chain of tapered capsules hanging from the body.

    Joint ``i`` rotates segment ``i`` and everything after it about
    ``bend_axis`` (body frame) by ``rest[i] + amp[i] * sin(2 pi freq t + phase - i lag)``;
    the whole limb also swings about ``swing_axis`` by ``swing * sin(2 pi freq t + phase)``.
    """

    name: str
    attach: tuple[float, float, float]
    direction: tuple[float, float, float]
    bend_axis: tuple[float, float, float]
    lengths: tuple[float, ...]
    radii: tuple[float, ...]  # one more than lengths
    rest: tuple[float, ...]
    amp: tuple[float, ...]
    swing_axis: tuple[float, float, float] = (0.0, 0.0, 1.0)
    swing: float = 0.0
    phase: float = 0.0
    lag: float = 0.4
    freq: float = 0.8


@dataclass(frozen=True, eq=False)
class Creature:
    """An animated articulated creature; :meth:`pose` evaluates it at a time.

    Parameters
    ----------
    name : str
        Subject name.
    body : tuple of (p0, p1, r0, r1)
        Body capsules in the body frame.
    limbs : tuple of LimbSpec
    base : (3,) float
        Body-frame origin in the world at rest (mm).
    motion : dict
        Body motion amplitudes: ``shift`` (3,) mm, ``yaw``, ``pitch``, ``roll`` radians, ``period`` s.
    tuck_pair : (str, str) or None
        Limbs pressed together by ``tuck`` (the first moves onto the second).
    tuck, spur : (float, float) or None
        Time intervals of the hard cases (see the module docstring).
    """

    name: str
    body: tuple
    limbs: tuple[LimbSpec, ...]
    base: tuple[float, float, float]
    motion: dict
    tuck_pair: tuple[str, str] | None = None
    tuck: tuple[float, float] | None = None
    spur: tuple[float, float] | None = None

    @property
    def names(self) -> list[str]:
        """Limb ids, in label order."""
        return [lb.name for lb in self.limbs]

    def _body_transform(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        m = self.motion
        w = 2 * math.pi / m["period"]
        shift = np.asarray(m["shift"], dtype=np.float64)
        pos = np.asarray(self.base, dtype=np.float64) + shift * np.array(
            [math.sin(w * t), math.sin(w * t + 1.3), math.sin(2 * w * t + 0.4)]
        )
        R = (
            _rot((0, 0, 1), m["yaw"] * math.sin(w * t + 0.5))
            @ _rot((0, 1, 0), m["pitch"] * math.sin(w * t + 2.0))
            @ _rot((1, 0, 0), m["roll"] * math.sin(w * t + 0.9))
        )
        return pos, R

    @staticmethod
    def _weight(t: float, interval: tuple[float, float] | None, ramp: float) -> float:
        if interval is None:
            return 0.0
        t0, t1 = interval
        if t0 <= t < t1:
            return 1.0
        if ramp <= 0:
            return 0.0
        d = (t0 - t) if t < t0 else (t - t1)
        if d >= ramp:
            return 0.0
        x = 1.0 - d / ramp
        return x * x * (3 - 2 * x)

    def _limb_chain(self, lb: LimbSpec, t: float) -> np.ndarray:
        """(S+1, 3) joint positions of a limb in the body frame."""
        return self._limb_frames(lb, t)[0]

    @staticmethod
    def _limb_frames(lb: LimbSpec, t: float) -> tuple[np.ndarray, np.ndarray]:
        """(S+1, 3) joint positions and (S, 3, 3) segment rotations of a limb in the body frame
        (segment ``i`` is its straight rest direction turned by rotation ``i``, from joint ``i``)."""
        w = 2 * math.pi * lb.freq
        R_swing = _rot(lb.swing_axis, lb.swing * math.sin(w * t + lb.phase)) if lb.swing else np.eye(3)
        d0 = _unit(lb.direction)
        axis = _unit(lb.bend_axis)
        pts = [np.asarray(lb.attach, dtype=np.float64)]
        rots = []
        theta = 0.0
        for i, L in enumerate(lb.lengths):
            theta += lb.rest[i] + lb.amp[i] * math.sin(w * t + lb.phase - i * lb.lag)
            rots.append(R_swing @ _rot(axis, theta))
            pts.append(pts[-1] + L * (rots[-1] @ d0))
        return np.stack(pts), np.stack(rots)

    def _capsule_frames(self, chains: dict, rots: dict, R: np.ndarray, pos: np.ndarray, spur: bool):
        """World frames (R (M, 3, 3), o (M, 3)) of the capsules, in the pose's order: body capsules
        move with the body, limb segment ``i`` with its rotation about joint ``i``."""
        Rs = [R] * len(self.body)
        Os = [pos] * len(self.body)
        for lb in self.limbs:
            for i in range(len(lb.lengths)):
                Rs.append(R @ rots[lb.name][i])
                Os.append(R @ chains[lb.name][i] + pos)
        if spur:
            Rs.append(R)
            Os.append(pos)
        return np.stack(Rs), np.stack(Os)

    def _rest_motions(self, frames: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
        """(M, 3, 4) ``[R | t]`` per capsule: from its place at rest (time 0, no hard case) to ``frames``."""
        pos0, R0 = self._body_transform(0.0)
        limb0 = {lb.name: self._limb_frames(lb, 0.0) for lb in self.limbs}
        F0, O0 = self._capsule_frames({k: v[0] for k, v in limb0.items()}, {k: v[1] for k, v in limb0.items()},
                                      R0, pos0, spur=len(frames[0]) > self._n_plain_capsules)
        Rt = np.einsum("mij,mkj->mik", frames[0], F0)  # R_t R_0^T
        t = frames[1] - np.einsum("mij,mj->mi", Rt, O0)
        return np.concatenate([Rt, t[:, :, None]], axis=2)

    @property
    def _n_plain_capsules(self) -> int:
        return len(self.body) + sum(len(lb.lengths) for lb in self.limbs)

    def _tucked_chain(self, chains: dict, rots: np.ndarray, w: float) -> tuple[np.ndarray, np.ndarray]:
        """The first limb of ``tuck_pair`` pressed onto the second, by weight ``w`` in 0..1.

        ``chains``: limb -> (S+1, 3) joints in the body frame; ``rots``: (S, 3, 3) segment
        rotations of the first limb (changed in place). Its junction stays; the other joints
        are blended towards a line beside the second limb, then re-extended to the segment
        lengths, each segment turning rigidly onto its new direction (its texture goes with it).
        -> ((S+1, 3) joints, (S, 3, 3) rotations) of the first limb.
        """
        a_name, b_name = self.tuck_pair
        la = next(lb for lb in self.limbs if lb.name == a_name)
        lbb = next(lb for lb in self.limbs if lb.name == b_name)
        A, B = chains[a_name], chains[b_name]
        side = A[0] - B[0]
        dB = _unit(B[-1] - B[0])
        side = side - dB * (side @ dB)
        side = _unit(side) if np.linalg.norm(side) > 1e-9 else np.array([0.0, 1.0, 0.0])
        gap = 0.85 * (max(la.radii) + max(lbb.radii))
        target = B + gap * side
        A2 = A.copy()
        # keep the junction, move the rest of the limb next to the other one
        A2[1:] = (1 - w) * A[1:] + w * target[1:]
        # keep segment lengths (re-extend along the blended directions)
        for i in range(1, len(A2)):
            d = A2[i] - A2[i - 1]
            A2[i] = A2[i - 1] + _unit(d) * la.lengths[i - 1]
            rots[i - 1] = _align(A[i] - A[i - 1], A2[i] - A2[i - 1]) @ rots[i - 1]
        return A2, rots

    def _spur_capsule(self) -> tuple:
        """(p0, p1, r0, r1) in the body frame of the hard case ``spur``: a short stub growing out
        of the body, a spurious protrusion."""
        a, b, ra, rb = self.body[0]
        a = np.asarray(a, dtype=np.float64)
        out_dir = _unit(np.asarray(self.motion.get("spur_dir", (0.3, 0.6, 0.74))))
        return a, a + out_dir * (ra + 0.9 * ra), 0.45 * ra, 0.3 * ra

    def pose(self, time_s: float) -> Pose:
        """The creature at ``time_s`` seconds.

        Returns
        -------
        Pose
            With ``rest``: every capsule's rigid motion from its place at time 0 (without the
            hard cases), so that the renderer paints the texture on the body.
        """
        t = float(time_s)
        if not math.isfinite(t):
            raise ValueError(f"time_s must be finite, got {time_s!r}")
        pos, R = self._body_transform(t)
        p0, p1, r0, r1, lab = [], [], [], [], []
        for a, b, ra, rb in self.body:
            p0.append(a)
            p1.append(b)
            r0.append(ra)
            r1.append(rb)
            lab.append(BODY)
        limb_frames = {lb.name: self._limb_frames(lb, t) for lb in self.limbs}
        chains = {k: v[0] for k, v in limb_frames.items()}
        rots = {k: v[1].copy() for k, v in limb_frames.items()}
        w_tuck = self._weight(t, self.tuck, 0.1) if self.tuck_pair else 0.0
        if w_tuck > 0:
            a_name = self.tuck_pair[0]
            chains[a_name], rots[a_name] = self._tucked_chain(chains, rots[a_name], w_tuck)
        tips, axes = {}, {}
        for li, lb in enumerate(self.limbs):
            P = chains[lb.name]
            for i in range(len(lb.lengths)):
                p0.append(P[i])
                p1.append(P[i + 1])
                r0.append(lb.radii[i])
                r1.append(lb.radii[i + 1])
                lab.append(li)
            tip_local = P[-1] + lb.radii[-1] * _unit(P[-1] - P[-2])
            axes[lb.name] = np.vstack([P, tip_local[None]]) @ R.T + pos
            tips[lb.name] = tip_local @ R.T + pos
        spur = self._weight(t, self.spur, 0.0) > 0
        if spur:
            for lst, v in zip((p0, p1, r0, r1, lab), (*self._spur_capsule(), BODY)):
                lst.append(v)
        P0 = np.asarray(p0) @ R.T + pos
        P1 = np.asarray(p1) @ R.T + pos
        return Pose(
            p0=P0,
            p1=P1,
            r0=np.asarray(r0),
            r1=np.asarray(r1),
            limb=np.asarray(lab),
            names=tuple(self.names),
            tips=tips,
            axes=axes,
            time=t,
            rest=self._rest_motions(self._capsule_frames(chains, rots, R, pos, spur)),
        )


# -- the subjects -------------------------------------------------------------


def _starfish(rng: np.random.Generator) -> dict:
    limbs = []
    for i in range(5):
        ang = 2 * math.pi * i / 5 + rng.uniform(-0.08, 0.08)
        radial = (math.cos(ang), math.sin(ang), 0.0)
        tangent = (-math.sin(ang), math.cos(ang), 0.0)
        # positive rotation about -tangent lifts the arm (curls up)
        bend = tuple(-c for c in tangent)
        limbs.append(
            LimbSpec(
                name=f"arm{i}",
                attach=(45.0 * radial[0], 45.0 * radial[1], 0.0),
                direction=radial,
                bend_axis=bend,
                lengths=(45.0, 42.0, 40.0, 36.0),
                radii=(30.0, 25.0, 19.0, 14.0, 9.0),
                rest=(0.12, 0.15, 0.18, 0.2),
                amp=tuple(float(a) for a in rng.uniform(0.12, 0.2, size=4)),
                swing_axis=(0.0, 0.0, 1.0),
                swing=float(rng.uniform(0.1, 0.18)),
                phase=2 * math.pi * i / 5 + float(rng.uniform(-0.3, 0.3)),
                lag=0.5,
                freq=0.6,
            )
        )
    body = []
    for i in range(5):
        ang = 2 * math.pi * (i + 0.5) / 5
        body.append(((0.0, 0.0, 8.0), (28.0 * math.cos(ang), 28.0 * math.sin(ang), 0.0), 40.0, 32.0))
    return dict(
        body=tuple(body),
        limbs=tuple(limbs),
        base=(0.0, 0.0, 58.0),
        motion=dict(shift=(25.0, 25.0, 8.0), yaw=0.25, pitch=0.06, roll=0.06, period=4.0),
        tuck_pair=("arm1", "arm0"),
    )


def _quadruped(rng: np.random.Generator) -> dict:
    limbs = []
    lat = (0.0, 1.0, 0.0)
    gait = {"fl": 0.0, "hr": 0.0, "fr": math.pi, "hl": math.pi}
    for key, x, y in (("fl", 85.0, 42.0), ("fr", 85.0, -42.0), ("hl", -85.0, 42.0), ("hr", -85.0, -42.0)):
        front = x > 0
        limbs.append(
            LimbSpec(
                name=f"leg_{key}",
                attach=(x, y, -25.0),
                direction=(0.0, 0.0, -1.0),
                bend_axis=lat,
                lengths=(85.0, 80.0, 28.0),
                radii=(30.0, 20.0, 14.0, 11.0),
                rest=(-0.1, 0.25, -0.35) if front else (0.15, -0.4, 0.45),
                amp=(0.08, 0.12 if front else -0.12, 0.0),
                swing_axis=lat,
                swing=0.25,
                phase=gait[key] + float(rng.uniform(-0.1, 0.1)),
                lag=0.6,
                freq=1.0,
            )
        )
    limbs.append(
        LimbSpec(
            name="head",
            attach=(115.0, 0.0, 15.0),
            direction=(0.75, 0.0, 0.66),
            bend_axis=lat,
            lengths=(55.0, 60.0),
            radii=(30.0, 27.0, 17.0),
            rest=(0.0, 0.9),
            amp=(0.12, 0.1),
            swing_axis=(0.0, 0.0, 1.0),
            swing=0.35,
            phase=float(rng.uniform(0, 2 * math.pi)),
            freq=0.5,
        )
    )
    limbs.append(
        LimbSpec(
            name="tail",
            attach=(-120.0, 0.0, 15.0),
            direction=(-0.85, 0.0, 0.52),
            bend_axis=(0.0, 0.0, 1.0),
            lengths=(40.0, 38.0, 36.0),
            radii=(15.0, 12.0, 9.0, 6.0),
            rest=(0.0, 0.05, 0.05),
            amp=(0.25, 0.3, 0.35),
            swing_axis=lat,
            swing=0.15,
            phase=float(rng.uniform(0, 2 * math.pi)),
            lag=0.7,
            freq=1.5,
        )
    )
    body = (
        ((-95.0, 0.0, 0.0), (95.0, 0.0, 5.0), 58.0, 62.0),
        ((60.0, 0.0, 10.0), (115.0, 0.0, 15.0), 50.0, 36.0),
    )
    return dict(
        body=body,
        limbs=tuple(limbs),
        base=(0.0, 0.0, 240.0),
        motion=dict(shift=(40.0, 30.0, 6.0), yaw=0.3, pitch=0.04, roll=0.03, period=4.0, spur_dir=(0.0, 0.55, 0.84)),
        tuck_pair=("leg_fl", "leg_fr"),
    )


def _tailed_quadruped(rng: np.random.Generator) -> dict:
    spec = _quadruped(rng)
    limbs = list(spec["limbs"])
    i = next(j for j, lb in enumerate(limbs) if lb.name == "tail")
    # diameters 36, 30, 24, 16 mm; longer than the quadruped's so it stands clear of the body
    limbs[i] = LimbSpec(**{**limbs[i].__dict__, "lengths": (50.0, 48.0, 46.0), "radii": (18.0, 15.0, 12.0, 8.0)})
    # the tail is absolute: a larger animal has the same thin tail (lengths and thickness)
    return {**spec, "limbs": tuple(limbs), "fixed_size": ("tail",)}


def _biped(rng: np.random.Generator) -> dict:
    limbs = []
    for side, y in (("l", 1.0), ("r", -1.0)):
        ph = 0.0 if side == "l" else math.pi
        limbs.append(
            LimbSpec(
                name=f"arm_{side}",
                attach=(0.0, 60.0 * y, 130.0),
                direction=(0.0, 0.25 * y, -1.0),
                bend_axis=(0.0, 1.0, 0.0),
                lengths=(95.0, 90.0),
                radii=(24.0, 18.0, 13.0),
                rest=(0.0, 0.35),
                amp=(0.0, 0.2),
                swing_axis=(0.0, 1.0, 0.0),
                swing=0.45,
                phase=ph + math.pi + float(rng.uniform(-0.1, 0.1)),
                lag=0.8,
                freq=0.8,
            )
        )
        limbs.append(
            LimbSpec(
                name=f"leg_{side}",
                attach=(0.0, 40.0 * y, -10.0),
                direction=(0.0, 0.0, -1.0),
                bend_axis=(0.0, 1.0, 0.0),
                lengths=(110.0, 105.0),
                radii=(34.0, 25.0, 17.0),
                rest=(0.1, -0.25),
                amp=(0.0, -0.2),
                swing_axis=(0.0, 1.0, 0.0),
                swing=0.35,
                phase=ph + float(rng.uniform(-0.1, 0.1)),
                lag=1.2,
                freq=0.8,
            )
        )
    limbs.insert(
        0,
        LimbSpec(
            name="head",
            attach=(0.0, 0.0, 145.0),
            direction=(0.1, 0.0, 1.0),
            bend_axis=(0.0, 1.0, 0.0),
            lengths=(25.0, 50.0),
            radii=(22.0, 36.0, 32.0),
            rest=(0.0, 0.0),
            amp=(0.08, 0.05),
            swing_axis=(0.0, 0.0, 1.0),
            swing=0.3,
            phase=float(rng.uniform(0, 2 * math.pi)),
            freq=0.4,
        ),
    )
    body = (((0.0, 0.0, 0.0), (0.0, 0.0, 130.0), 50.0, 58.0),)
    return dict(
        body=body,
        limbs=tuple(limbs),
        base=(0.0, 0.0, 265.0),
        motion=dict(shift=(50.0, 30.0, 5.0), yaw=0.35, pitch=0.03, roll=0.05, period=5.0, spur_dir=(1.0, 0.0, 0.3)),
        tuck_pair=("arm_l", "leg_l"),
    )


_BUILDERS = {"starfish": _starfish, "quadruped": _quadruped, "biped": _biped, "tailed_quadruped": _tailed_quadruped}


def _scaled(spec: dict, s: float) -> dict:
    def sc(v):
        return tuple(float(x) * s for x in v)

    body = tuple((sc(a), sc(b), ra * s, rb * s) for a, b, ra, rb in spec["body"])
    fixed = spec.get("fixed_size", ())
    limbs = tuple(
        LimbSpec(**{**lb.__dict__, "attach": sc(lb.attach), **({} if lb.name in fixed else
                                                               {"lengths": sc(lb.lengths), "radii": sc(lb.radii)})})
        for lb in spec["limbs"]
    )
    motion = dict(spec["motion"])
    motion["shift"] = sc(motion["shift"])
    return {**spec, "body": body, "limbs": limbs, "base": sc(spec["base"]), "motion": motion}


def _interval(value, name: str) -> tuple[float, float] | None:
    if value is None:
        return None
    try:
        t0, t1 = (float(v) for v in value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a (start, stop) time interval in seconds, got {value!r}") from None
    if not (math.isfinite(t0) and math.isfinite(t1)) or t1 <= t0:
        raise ValueError(f"{name} must be a (start, stop) interval with start < stop, got {value!r}")
    return (t0, t1)


def make_creature(
    name: str,
    *,
    scale: float = 1.0,
    seed: int = 0,
    tuck: tuple[float, float] | None = None,
    spur: tuple[float, float] | None = None,
    origin: tuple[float, float] = (0.0, 0.0),
) -> Creature:
    """An animated creature standing on the floor (z = 0) at ``origin``.

    Parameters
    ----------
    name : {"starfish", "quadruped", "biped", "tailed_quadruped"}
    scale : float, optional
        Uniform size factor (1.0: a span of about 300-500 mm that moves
        within the default 750 mm volume), 0.2..2.
    seed : int, optional
        Varies phases and amplitudes of the motion a little.
    tuck : (float, float), optional
        Time interval (s) during which the creature's ``tuck_pair`` limbs are
        pressed together.
    spur : (float, float), optional
        Time interval (s) during which a spurious protrusion sticks out of the body.
    origin : (float, float), optional
        Floor position (x, y) of the creature's rest pose, mm.

    Returns
    -------
    Creature
    """
    if name not in _BUILDERS:
        raise ValueError(f"name must be one of {', '.join(CREATURES)}, got {name!r}")
    try:
        s = float(scale)
    except (TypeError, ValueError):
        raise ValueError(f"scale must be a number, got {scale!r}") from None
    if not 0.2 <= s <= 2.0:
        raise ValueError(f"scale must be within 0.2..2, got {scale!r}")
    try:
        ox, oy = (float(v) for v in origin)
    except (TypeError, ValueError):
        raise ValueError(f"origin must be (x, y) in mm, got {origin!r}") from None
    spec = _scaled(_BUILDERS[name](np.random.default_rng(seed)), s)
    bx, by, bz = spec["base"]
    spec["base"] = (bx + ox, by + oy, bz)
    return Creature(
        name=name,
        body=spec["body"],
        limbs=spec["limbs"],
        base=spec["base"],
        motion=spec["motion"],
        tuck_pair=spec["tuck_pair"],
        tuck=_interval(tuck, "tuck"),
        spur=_interval(spur, "spur"),
    )
