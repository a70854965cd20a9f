"""A unicycle robot driving a route: speed, turn-rate and acceleration limits, simulated in fixed time steps.

State ``(x, y, yaw, v, omega)`` in the world frame (metres, radians; yaw CCW about +z, kept continuous, not wrapped).
Each step of :data:`STEP_US` microseconds first moves ``v`` and ``omega`` towards their commands by at most
``accel * dt`` and ``turn_accel * dt``, then integrates ``x += v cos(yaw_mid) dt``, ``y += v sin(yaw_mid) dt``,
``yaw += omega dt`` (``yaw_mid`` the heading half a step on).

The drive, in order:

1. **look-around**: one full turn in place (CCW, ``2 pi``), trapezoidal in ``omega``;
2. **follow** the waypoints, heading along the path tangent: the heading error ``e`` is the angle to a look-ahead
   point ``lookahead`` metres further along the path. When ``|e|`` exceeds ``turn_in_place_deg`` the robot brakes and
   turns in place until ``|e| < aligned_deg``; otherwise it drives at up to ``speed`` with ``omega = clip(gain * e)``.
   The speed is capped by ``sqrt(2 accel d)`` for the distance ``d`` to the goal and to the next corner sharper than
   ``turn_in_place_deg``, so the robot can stop there;
3. stop within ``goal_tolerance`` of the goal.

The simulation is a pure function of its inputs; frames at any rate sample it (:func:`sample_poses`), so a 10 Hz stream
is every second frame of the 20 Hz stream of the same route.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

#: Simulation step (microseconds): 100 Hz. Frame times that are whole steps need no interpolation.
STEP_US = 10_000


@dataclasses.dataclass(frozen=True)
class Limits:
    """Motion limits and the path follower's settings (metres, seconds, radians unless named ``_deg``).

    ``speed`` (v_max, m/s), ``turn_rate`` (omega_max, rad/s), ``accel`` (a_max, m/s^2) are the protocol's;
    ``turn_accel`` (rad/s^2) is ours (the protocol names none; without one omega would jump).
    """

    speed: float = 0.5
    turn_rate: float = 1.0
    accel: float = 0.5
    turn_accel: float = 2.0
    turn_in_place_deg: float = 30.0
    aligned_deg: float = 5.0
    lookahead: float = 0.4
    gain: float = 2.0
    goal_tolerance: float = 0.05

    def __post_init__(self) -> None:
        if self.speed < 0 or self.turn_rate < 0:
            raise ValueError("speed and turn_rate must be >= 0")
        if self.accel <= 0 or self.turn_accel <= 0:
            raise ValueError("accel and turn_accel must be > 0")
        if self.speed > 0 and self.turn_rate == 0:
            raise ValueError("a robot that drives (speed > 0) must be able to turn (turn_rate > 0)")
        if not 0 < self.aligned_deg < self.turn_in_place_deg < 180:
            raise ValueError("need 0 < aligned_deg < turn_in_place_deg < 180")
        if self.lookahead <= 0 or self.gain <= 0 or self.goal_tolerance <= 0:
            raise ValueError("lookahead, gain and goal_tolerance must be > 0")


@dataclasses.dataclass(frozen=True, eq=False)
class Trajectory:
    """States every :data:`STEP_US`: ``xy`` (T,2) world metres, ``yaw`` (T,) radians (continuous), ``v`` (T,) m/s,
    ``omega`` (T,) rad/s; state k is at ``k * STEP_US`` microseconds."""

    xy: np.ndarray
    yaw: np.ndarray
    v: np.ndarray
    omega: np.ndarray

    @property
    def end_us(self) -> int:
        """Time of the last state (microseconds)."""
        return (len(self.yaw) - 1) * STEP_US


class _Sim:
    """The integrator and its recorded states."""

    def __init__(self, xy: np.ndarray, yaw: float, limits: Limits, max_steps: int):
        self.x, self.y = float(xy[0]), float(xy[1])
        self.yaw, self.v, self.w = float(yaw), 0.0, 0.0
        self.limits = limits
        self.max_steps = max_steps
        self.states = [(self.x, self.y, self.yaw, self.v, self.w)]

    def step(self, v_cmd: float, w_cmd: float) -> None:
        if len(self.states) > self.max_steps:
            raise RuntimeError("the robot did not reach its goal in time")
        dt = STEP_US * 1e-6
        lim = self.limits
        self.v += min(max(v_cmd - self.v, -lim.accel * dt), lim.accel * dt)
        self.w += min(max(w_cmd - self.w, -lim.turn_accel * dt), lim.turn_accel * dt)
        mid = self.yaw + self.w * dt / 2
        self.x += self.v * math.cos(mid) * dt
        self.y += self.v * math.sin(mid) * dt
        self.yaw += self.w * dt
        self.states.append((self.x, self.y, self.yaw, self.v, self.w))

    def turn_by(self, angle: float) -> None:
        """Turn in place by ``angle`` radians (trapezoidal omega), ending at rest."""
        lim = self.limits
        target = self.yaw + angle
        dw = lim.turn_accel * STEP_US * 1e-6
        while True:
            rem = target - self.yaw
            if abs(rem) < 1e-3 and abs(self.w) <= dw and self.v == 0.0:
                break
            w_cmd = math.copysign(min(lim.turn_rate, math.sqrt(2 * lim.turn_accel * abs(rem))), rem)
            self.step(0.0, w_cmd)
        self.w = 0.0

    def follow(self, waypoints: np.ndarray) -> None:
        """Drive along ``waypoints`` (K,2) to the last one (see the module docstring), ending at rest."""
        lim = self.limits
        p = np.asarray(waypoints, dtype=np.float64)
        seg = np.diff(p, axis=0)
        seg_len = np.linalg.norm(seg, axis=1)
        s_at = np.concatenate([[0.0], np.cumsum(seg_len)])
        total = float(s_at[-1])
        heading = np.arctan2(seg[:, 1], seg[:, 0])
        turn = np.abs((np.diff(heading) + np.pi) % (2 * np.pi) - np.pi)  # at waypoints 1 .. K-2
        sharp = s_at[1:-1][turn > math.radians(lim.turn_in_place_deg)]
        goal = p[-1]
        s_prog, k = 0.0, 0
        turning = arrived = False
        while True:
            # progress: the nearest point on segments k .. k+2, never behind the current progress
            best, best_d = s_prog, math.inf
            for j in range(k, min(k + 3, len(seg))):
                if seg_len[j] == 0:
                    continue
                u = ((self.x - p[j, 0]) * seg[j, 0] + (self.y - p[j, 1]) * seg[j, 1]) / seg_len[j] ** 2
                u = min(max(u, 0.0), 1.0)
                d = math.hypot(p[j, 0] + u * seg[j, 0] - self.x, p[j, 1] + u * seg[j, 1] - self.y)
                if d < best_d:
                    best, best_d = s_at[j] + u * seg_len[j], d
            s_prog = max(s_prog, best)
            while k < len(seg) - 1 and s_at[k + 1] <= s_prog:
                k += 1
            d_goal = math.hypot(goal[0] - self.x, goal[1] - self.y)
            arrived = arrived or d_goal < lim.goal_tolerance or s_prog >= total - lim.goal_tolerance
            if arrived:  # brake to rest (v and omega reach exactly 0: the last step subtracts what is left)
                if self.v == 0.0 and self.w == 0.0:
                    break
                self.step(0.0, 0.0)
                continue
            s_look = min(s_prog + lim.lookahead, total)
            j = min(int(np.searchsorted(s_at, s_look, side="right")) - 1, len(seg) - 1)
            u = (s_look - s_at[j]) / seg_len[j] if seg_len[j] > 0 else 0.0
            look = p[j] + u * seg[j]
            e = (math.atan2(look[1] - self.y, look[0] - self.x) - self.yaw + math.pi) % (2 * math.pi) - math.pi
            if turning and abs(e) < math.radians(lim.aligned_deg):
                turning = False
            elif not turning and abs(e) > math.radians(lim.turn_in_place_deg):
                turning = True
            if turning:
                self.step(0.0, math.copysign(min(lim.turn_rate, math.sqrt(2 * lim.turn_accel * abs(e))), e))
                continue
            ahead = sharp[sharp > s_prog]
            d_stop = min(d_goal, float(ahead[0] - s_prog) if len(ahead) else math.inf)
            v_cmd = min(lim.speed, math.sqrt(2 * lim.accel * max(d_stop, 0.0)))
            self.step(v_cmd, min(max(lim.gain * e, -lim.turn_rate), lim.turn_rate))

    def trajectory(self) -> Trajectory:
        s = np.array(self.states, dtype=np.float64)
        return Trajectory(xy=s[:, :2].copy(), yaw=s[:, 2].copy(), v=s[:, 3].copy(), omega=s[:, 4].copy())


def drive(waypoints: np.ndarray, start_yaw: float, limits: Limits, look_around: bool = True,
          hold_until_us: int = 0, max_seconds: float | None = None) -> Trajectory:
    """Simulate the drive of the module docstring from ``waypoints[0]`` (heading ``start_yaw``) to ``waypoints[-1]``.

    A single waypoint (or ``limits.speed == 0``) gives no translation; ``look_around`` needs ``turn_rate > 0``. The
    robot then stands still until ``hold_until_us`` if that is later. ``RuntimeError`` when the drive takes longer
    than ``max_seconds`` (default: 4 x the path at full speed plus 60 s).
    """
    p = np.asarray(waypoints, dtype=np.float64).reshape(-1, 2)
    length = float(np.linalg.norm(np.diff(p, axis=0), axis=1).sum())
    if max_seconds is None:
        max_seconds = 60.0 + (4.0 * length / limits.speed if limits.speed > 0 else 0.0)
    sim = _Sim(p[0], start_yaw, limits, max_steps=int(max_seconds * 1e6 / STEP_US))
    if look_around and limits.turn_rate > 0:
        sim.turn_by(2 * math.pi)
    if limits.speed > 0 and len(p) > 1 and length > 0:
        sim.follow(p)
    while len(sim.states) - 1 < hold_until_us // STEP_US + (hold_until_us % STEP_US > 0):
        sim.states.append((sim.x, sim.y, sim.yaw, 0.0, 0.0))
    return sim.trajectory()


def frame_times(rate: float, end_us: int) -> np.ndarray:
    """(N,) int64 capture times ``round(i * 1e6 / rate)`` microseconds for i = 0, 1, ... while ``<= end_us``."""
    if rate <= 0:
        raise ValueError("rate must be > 0 Hz")
    n = int(math.floor(end_us * rate / 1e6 + 1e-9)) + 1
    t = np.round(np.arange(n + 1) * (1e6 / rate)).astype(np.int64)
    return t[t <= end_us]


def sample_poses(traj: Trajectory, times_us: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(xy (N,2), yaw (N,))`` at ``times_us`` (within the trajectory), linear between the two enclosing states."""
    t = np.asarray(times_us, dtype=np.int64)
    k = np.minimum(t // STEP_US, len(traj.yaw) - 1)
    f = ((t - k * STEP_US) / STEP_US)[:, None]
    k1 = np.minimum(k + 1, len(traj.yaw) - 1)
    xy = traj.xy[k] * (1 - f) + traj.xy[k1] * f
    yaw = traj.yaw[k] * (1 - f[:, 0]) + traj.yaw[k1] * f[:, 0]
    return xy, yaw
