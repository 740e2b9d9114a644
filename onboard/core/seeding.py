"""The linearization trajectory of a period: steady inputs from the slots, candidate input
sequences and the choice among them (docs/design.md, "Controller": "Linearization seed" and
"Steady inputs from the slots").

The QP is linearized along a trajectory chosen from candidates (the steady inputs u_s, a pursuit
of the slot, the previous plan shifted by one step), each clipped to the tube-tightened U, rolled
out with the learned model and scored against the goal; hysteresis keeps the incumbent, and the
pursuit keeps turning the way it turned toward a goal behind, so the seed does not alternate.
Plain floats throughout: the horizon is a handful of points.
"""

import math

from fleetmpc.onboard.core.config import ControllerSettings
from fleetmpc.onboard.core.tube import InputBox
from fleetmpc.onboard.core.unicycle import advance, wrap

__all__ = ["Seeder"]

_TWO_PI = 2.0 * math.pi

_BEHIND_RAD = 2.0
"""A pursuit whose goal lies more than this far off the nose keeps turning the way it turned the
period before (a goal right behind is as near turning left as right)."""


class Seeder:
    """Seeds the linearization of one vehicle's QP, period after period (it remembers the way the
    pursuit turned)."""

    def __init__(
        self,
        controller: ControllerSettings,
        box: InputBox,
    ) -> None:
        self.settings = controller
        self.box = box
        """U and its tube-tightened box of each step j (`InputBox.steps`)."""
        self._turn_sign = 0
        """The way the pursuit seed turned toward a goal behind (+1, -1), 0 when it was not."""

    def steady_inputs(
        self, slots: list[tuple[float, float]], beta: list[float], yaw: float
    ) -> tuple[list[tuple[float, float]], list[float]]:
        """u_s (M pairs) and steady headings (M + 1) keeping the learned model on slots (M + 2).

        The ground velocity between consecutive slots, less the learned drift, gives the speed and
        the course of each chord (a (nearly) still slot keeps the vehicle's heading). The model
        flies a step along its midpoint heading (`fleetmpc.onboard.core.unicycle`), so the heading
        at a slot is the mean of the courses of the chords either side of it, and a step along a
        chord then keeps to it (exactly, when the slots turn steadily). Headings are unwrapped.
        Each u_s,j is clipped to the tightened box of step j: slots that jump within a horizon (as
        they do the period a formation's first course is known) would otherwise ask for tens of
        m/s, which the cost would then pull every input toward.
        """
        tau = self.settings.period_s
        a_v, a_w, d_x, d_y = beta
        speeds, courses = [], []
        (x0, y0), raw_last = slots[0], None
        for x1, y1 in slots[1:]:
            gx, gy = (x1 - x0) / tau - d_x, (y1 - y0) / tau - d_y
            speed = math.hypot(gx, gy)
            raw = math.atan2(gy, gx) if speed >= 1e-3 else yaw
            courses.append(raw if raw_last is None else courses[-1] + wrap(raw - raw_last))
            raw_last, x0, y0 = raw, x1, y1
            speeds.append(speed)
        c0, c1 = courses[0], courses[1]
        ahead = zip(courses, courses[1:], strict=False)
        headings = [c0 - 0.5 * (c1 - c0)] + [0.5 * (a + b) for a, b in ahead]
        tw = tau * a_w
        steps = zip(speeds, headings, headings[1:], strict=False)
        u_s = [
            (min(v / a_v, v_hi), max(w_lo, min(w_hi, (h1 - h0) / tw)))
            for (v, h0, h1), (_, w_lo, v_hi, w_hi) in zip(steps, self.box.steps, strict=True)
        ]  # (M pairs)
        return u_s, headings

    def pursuit_inputs(
        self,
        z0: list[float],
        slots: list[tuple[float, float]],
        slot_vel: tuple[float, float],
        beta: list[float],
    ) -> list[tuple[float, float]]:
        """Inputs of a simple pursuit of the slot, to seed the linearization from far away.

        A goal (nearly) behind the vehicle is turned toward the way it was the period before,
        so that the seed does not flip between a left and a right turn.
        """
        s, tau = self.settings, self.settings.period_s
        a_v, a_w, d_x, d_y = beta
        x, y, th = z0
        vx, vy = slot_vel
        v_max, w_max = s.speed_max_m_s, s.yaw_rate_max_rad_s
        out = []
        turn = self._turn_sign
        for j, (sx, sy) in enumerate(slots[1 : s.horizon + 1]):
            gx, gy = vx + 0.5 * (sx - x) - d_x, vy + 0.5 * (sy - y) - d_y
            err = wrap(math.atan2(gy, gx) - th)
            if abs(err) > _BEHIND_RAD:
                if turn and err * turn < 0:
                    err += _TWO_PI * turn
                turn = 1 if err > 0 else -1
            elif j == 0:
                turn = 0
            if j == 0:
                self._turn_sign = turn
            v = math.hypot(gx, gy) / a_v * max(math.cos(err), 0.0)
            w = max(-w_max, min(w_max, err / (tau * a_w)))
            out.append((min(v, v_max), w))
            x, y, th = advance(x, y, th, out[-1][0], w, beta, tau)
        return out

    def seed(
        self,
        z0: list[float],
        candidates: list[list[tuple[float, float]]],
        beta: list[float],
        goal: list[tuple[float, float]],
        *,
        incumbent: int | None,
    ) -> tuple[list[tuple[float, float, float]], list[tuple[float, float]]]:
        """The linearization trajectory: (states, inputs) of one candidate input sequence.

        Each candidate is clipped to the tube-tightened U with its speed kept at least
        min_linearization_speed_m_s, rolled out with the learned model and scored by the
        squared distance of its positions to the goal (M points). The incumbent (the previous
        plan, shifted) is kept unless another candidate scores at most seed_switch_ratio of it.
        """
        s = self.settings
        v_min = s.min_linearization_speed_m_s
        scored = []
        for candidate in candidates:
            z = tuple(z0)
            states, inputs, cost = [z], [], 0.0
            steps = zip(candidate, goal, self.box.steps, strict=True)
            for (v, w), (gx, gy), (_, w_lo, v_hi, w_hi) in steps:
                v = max(v_min, min(v_hi, v))
                w = max(w_lo, min(w_hi, w))
                z = advance(*z, v, w, beta, s.period_s)
                states.append(z)
                inputs.append((v, w))
                cost += (z[0] - gx) ** 2 + (z[1] - gy) ** 2
            scored.append((cost, states, inputs))
        best = min(range(len(scored)), key=lambda i: scored[i][0])
        if incumbent is not None and scored[best][0] > s.seed_switch_ratio * scored[incumbent][0]:
            best = incumbent
        return scored[best][1], scored[best][2]
