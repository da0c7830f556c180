"""The body's translation from its pose and the pelvis accelerometer: where the pelvis is, not only how the body
is posed about it.

TransPose (Yi et al. 2021, §3.3) moves the root so that the foot on the ground stays where it is, and falls back
on a learned velocity when no foot is down. Here the same supporting-foot rule runs on the answer's own joint
positions, and the pelvis sensor takes the learned parts' place: whether a foot carries the body (with no foot
on the ground the body falls freely and the pelvis accelerometer's specific force drops towards 0, as in
running's flight phase or a jump; at the end of a push-off, while the foot still on the floor already rolls
off, it is well under 1 g; standing and most of walking keep it near 1 g or above), and which point is down
(the one whose standing still would move the pelvis most like its last velocity plus what the accelerometer
measured since).

Per frame each foot offers two contact points: its heel (the ankle, moved straight down by the ankle's height
over the ball of the foot in the neutral stance) and its ball (the toe joint). The candidates are the points
within ``CONTACT_BAND_M`` of the lowest; the chosen one holds still, so the pelvis moves by minus that point's
motion relative to the pelvis, averaged half and half with the inertial prediction (a complementary filter that
smooths the predicted legs' jitter). The floor is level at height 0 where the first frame's lowest point stands;
on the ground the lowest point stands on it, which sets the pelvis height (the vertical velocity is blended the
same way, so that a throw starts from a smooth one). Otherwise the pelvis moves as its accelerometer says (in
flight, a throw under gravity). A body starts at rest: a session that starts moving (an assignment hand-over
mid-walk) reads too little speed for its first frames, about five on the ground.

With a learned pelvis velocity (``training.pose.velocity``, TransPose's fallback network; ``translation:
learned``) that velocity stands in for the inertial prediction along the floor: it chooses the point, it moves
the body in flight, and on the ground it is averaged with the chosen point's velocity by ``learned_share``.

Known limits: the floor is flat (stairs, slopes and a seat read as the feet's level), a foot that slides moves
the body the other way, and error in the predicted legs accumulates as drift (docs/pose.md, "Translation").
The constants were set on training-side clips, not read off the held-out people (docs/pose.md says what those
were scored with while the rule was built).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from service.core.units import GRAVITY_MPS2

# Below this specific force at the pelvis (a fraction of g) no foot is taken to carry the body: flight, and the
# end of a push-off (set on the design set, docs/pose.md "Translation": 0.4 g, free fall only, read twice the
# error on fast runs; 0.9 g a little less than 0.8 g there, but leaves more frames to the accelerometer alone,
# whose real errors change within a session where the simulation's do not)
FLIGHT_SPECIFIC_FORCE_G = 0.8
# Contact candidates: points at most this far above the lowest one.
CONTACT_BAND_M = 0.03
# The share of the inertial prediction in each ground frame's velocity.
INERTIAL_SHARE = 0.5


@dataclass(frozen=True)
class Feet:
    """Which joint positions are each foot's ankle and ball, and the ankle's height over the ball when standing."""

    ankles: tuple[int, int]
    balls: tuple[int, int]
    ankle_height_m: float


@dataclass
class RootTracker:
    """One body's pelvis position frame after frame: ``advance`` takes any number of frames at a time (a stream
    keeps one tracker per session, ``advance_bodies`` moves many at once) and gives the same positions for a
    block in one call as in many."""

    feet: Feet
    sample_rate_hz: float
    # with a learned pelvis velocity: its share in each ground frame's horizontal velocity, the rest the chosen
    # point's (the velocity model's manifest gives the share chosen for it on validation subjects)
    learned_share: float = 0.5
    points: np.ndarray | None = field(default=None, repr=False)  # (4, 3) the last frame's contact points
    root: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0], repr=False)  # the last frame's pelvis
    velocity: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0], repr=False)  # m/s

    def advance(
        self, joints_m: np.ndarray, free_acc_pelvis_mps2: np.ndarray, learned_mps: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """Pelvis positions ``(T, 3)`` in the world the joints are given in (metres; x, y from the first frame's
        pelvis, z above the floor), and which point carries the body per frame (0 left heel, 1 left ball, 2 right
        heel, 3 right ball; -1 none: flight).

        joints_m: ``(T, S, 3)`` joint positions relative to the pelvis, world axes, z up; free_acc_pelvis_mps2:
        ``(T, 3)`` the pelvis's acceleration in the world without gravity (``calibration.segment_readings``);
        learned_mps: ``(T, 3)`` a learned pelvis velocity in the world (``training.pose.velocity``), which then
        takes the accelerometer's place along the floor: in flight it alone sets the velocity (the step from the
        last one integrated by the trapezoid rule), on the ground ``learned_share`` of it with the chosen point's,
        and it chooses that point; the height is the rule's either way."""
        learned = None if learned_mps is None else [learned_mps]
        return advance_bodies([self], [joints_m], [free_acc_pelvis_mps2], learned)[0]


def advance_bodies(
    trackers: list[RootTracker],
    joints_m: list[np.ndarray],
    free_acc_pelvis_mps2: list[np.ndarray],
    learned_mps: list[np.ndarray | None] | None = None,
) -> list[tuple[np.ndarray, np.ndarray]]:
    """``RootTracker.advance`` for several bodies (of one sample rate) at once: the array work of all their frames
    in one pass, so that a service with many live sessions pays numpy's per-call cost once per batch.
    ``learned_mps``: per body a learned velocity per frame, or None for a body moved by the rule alone."""
    counts = [len(j) for j in joints_m]
    learned_mps = learned_mps or [None] * len(trackers)
    sizes = [n if v is None else len(v) for n, v in zip(counts, learned_mps, strict=True)]
    if sizes != counts:
        raise ValueError(f"a learned velocity per frame: {sizes} for frames {counts}")
    bounds = np.cumsum([0, *counts])
    if not bounds[-1]:
        return [(np.zeros((0, 3)), np.zeros(0, dtype=int)) for _ in trackers]
    feet = trackers[0].feet  # every body's segments are named alike; the ankle heights differ with its size
    ankle_height = np.repeat([tr.feet.ankle_height_m for tr in trackers], counts)
    points = contact_points(np.concatenate(joints_m), feet.ankles, feet.balls, ankle_height)
    starting = [tr.points is None and n > 0 for tr, n in zip(trackers, counts, strict=True)]
    for tr, b, start in zip(trackers, bounds[:-1], starting, strict=True):
        if start:  # a body's first frame stands on the floor where it is, at rest
            tr.points = points[b].copy()
            tr.root = [0.0, 0.0, -float(points[b, :, 2].min())]
    before = np.concatenate([points[:1], points[:-1]])
    last = [tr.points for tr, n in zip(trackers, counts, strict=True) if n]
    before[bounds[:-1][np.asarray(counts) > 0]] = last
    rate = trackers[0].sample_rate_hz
    # Per frame and point, the pelvis velocity if that point held still; the heights; whether a foot is down.
    implied = ((before - points) * rate).tolist()
    heights = points[:, :, 2].tolist()
    acc = np.concatenate(free_acc_pelvis_mps2)
    specific_force = np.linalg.norm(acc + np.array([0.0, 0.0, GRAVITY_MPS2]), axis=-1)
    ground = (specific_force >= FLIGHT_SPECIFIC_FORCE_G * GRAVITY_MPS2).tolist()
    steps = (acc / rate).tolist()
    out: list[list[float]] = []
    carried: list[int] = []
    for tr, a, b, start, velocity in zip(
        trackers, bounds[:-1].tolist(), bounds[1:].tolist(), starting, learned_mps, strict=True
    ):
        if a == b:
            continue
        learned = None if velocity is None else velocity[int(start) :].tolist()
        if start:  # the first frame is the origin
            out.append(list(tr.root))
            carried.append(int(np.argmin(heights[a])) if ground[a] else -1)
        a += int(start)
        _track(tr, rate, implied[a:b], heights[a:b], ground[a:b], steps[a:b], out, carried, learned)
        tr.points = points[b - 1].copy()
    out_a, carried_a = np.array(out).reshape(-1, 3), np.array(carried, dtype=int)
    return [(out_a[a:b], carried_a[a:b]) for a, b in zip(bounds[:-1], bounds[1:], strict=True)]


def contact_points(
    joints_m: np.ndarray, ankles: tuple[int, int], balls: tuple[int, int], ankle_height_m: float | np.ndarray
) -> np.ndarray:
    """Heel and ball of the left foot, then of the right ``(T, 4, 3)``, from joint positions ``(T, S, 3)``: the
    heel is the ankle moved straight down by ``ankle_height_m`` (one, or one per frame)."""
    heels = joints_m[:, list(ankles)].copy()
    heels[..., 2] -= np.reshape(ankle_height_m, (-1, 1))
    balls_ = joints_m[:, list(balls)]
    return np.stack([heels[:, 0], balls_[:, 0], heels[:, 1], balls_[:, 1]], axis=1)


def _track(
    tr: RootTracker,
    rate: float,
    implied: list[list[list[float]]],
    heights: list[list[float]],
    ground: list[bool],
    steps: list[list[float]],
    out: list[list[float]],
    carried: list[int],
    learned: list[list[float]] | None = None,
) -> None:
    """One body's frames in order, appended to ``out`` and ``carried`` (Python floats: each frame's choice depends
    on the velocity before it). Per frame: ``implied`` the pelvis velocity if each point held still, ``heights`` the
    points' heights, ``ground`` whether a foot carries the body, ``steps`` the accelerometer's change of velocity,
    ``learned`` a learned velocity (then the prediction along the floor, and ``learned_share`` of its velocity)."""
    (x, y, z), (vx, vy, vz) = tr.root, tr.velocity
    share = INERTIAL_SHARE if learned is None else tr.learned_share
    for t in range(len(heights)):
        px, py, pz = vx + steps[t][0], vy + steps[t][1], vz + steps[t][2]  # the inertial prediction
        if learned is not None:
            px, py = learned[t][0], learned[t][1]
        j = -1
        if ground[t]:
            h = heights[t]
            low = min(h) + CONTACT_BAND_M
            j = min(
                (k for k in range(4) if h[k] <= low),
                key=lambda k: math.hypot(implied[t][k][0] - px, implied[t][k][1] - py),
            )
        if j >= 0:  # the chosen point moves the pelvis along the floor; the lowest one stands on it
            vx = share * px + (1.0 - share) * implied[t][j][0]
            vy = share * py + (1.0 - share) * implied[t][j][1]
            z_floor = -min(heights[t])
            vz = INERTIAL_SHARE * pz + (1.0 - INERTIAL_SHARE) * (z_floor - z) * rate
            x, y, z = x + vx / rate, y + vy / rate, z_floor
        else:  # a throw: exact for the acceleration held over the frame
            x, y, z = x + 0.5 * (vx + px) / rate, y + 0.5 * (vy + py) / rate, z + 0.5 * (vz + pz) / rate
            vx, vy, vz = px, py, pz
        out.append([x, y, z])
        carried.append(j)
    tr.root, tr.velocity = [x, y, z], [vx, vy, vz]
