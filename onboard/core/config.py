"""Frozen configuration of the onboard controller, validated at construction."""

import math
from dataclasses import dataclass

from fleetmpc.errors import ConfigError
from fleetmpc.validate import finite, in_range, positive, vector

__all__ = ["ControllerSettings", "FormationSettings", "LearningSettings"]


@dataclass(frozen=True)
class ControllerSettings:
    """Tube LBMPC settings (paper Sec. V-B, as corrected in docs/design.md, "Controller")."""

    period_s: float = 0.2
    """Control period tau [s]."""
    horizon: int = 5
    """Prediction horizon M [steps]."""
    speed_max_m_s: float = 2.0
    """Input box U: |forward speed| <= this [m/s]."""
    yaw_rate_max_rad_s: float = 0.5
    """Input box U: |yaw rate| <= this [rad/s]."""
    q_position: float = 4.0
    """Stage weight on the position error to the slot [1/m^2]."""
    q_heading: float = 0.2
    """Stage weight on the heading error to the steady-state heading [1/rad^2]."""
    q_formation: float = 1.0
    """Stage weight on each neighbour's relative-position error [1/m^2]."""
    r_speed: float = 1.0
    """Input weight on speed away from its steady-state value [s^2/m^2]."""
    r_yaw_rate: float = 1.0
    """Input weight on yaw rate away from its steady-state value [s^2/rad^2]."""
    w_position_m: float = 0.02
    """Disturbance box W: per-period bound on the position model error [m]."""
    w_heading_rad: float = 0.005
    """Disturbance box W: per-period bound on the heading model error [rad]."""
    d_safe_m: float = 2.0
    """Hard minimum separation between any two vehicles [m]."""
    reference_speed_m_s: float = 1.0
    """Cruise speed at which K and the tube are computed (never 0) [m/s]."""
    min_linearization_speed_m_s: float = 0.3
    """Smallest speed of a linearization point, so the lateral mode stays controllable [m/s]."""
    plan_extrapolation_s: float = 1.0
    """How far past its end a neighbour's plan is extrapolated [s]."""
    plan_stale_s: float = 1.0
    """Plan age beyond which a neighbour's formation term is dropped and it is taken to be
    silent: somewhere between its last plan and its slot (docs/design.md, "Silent
    neighbours") [s]."""
    plan_forget_s: float = 60.0
    """Plan age beyond which a neighbour is ignored entirely [s]."""
    silent_allowance_m: float = 1.0
    """Distance kept beyond the margin from a silent neighbour's region, for what its agent and
    this one see differently of the target and of its path to its slot [m]."""
    neighbours_max: int = 12
    """K: at most this many neighbours get separation constraints in a vehicle's QP, the
    nearest of those within its safety radius (docs/design.md, "Neighbourhood"); the QP's size
    does not grow with the fleet beyond it."""
    r_yaw_rate_change: float = 1.0
    """Input weight on the change of yaw rate from one step to the next [s^2/rad^2]: smooths the
    yaw-rate command (0: no such term)."""
    speed_rate_max_m_s2: float = 2.0
    """How fast a plan may change its speed [m/s^2]: planned stops take time, as real ones do."""
    yaw_rate_trust_rad_s: float = 0.25
    """Trust region of the QP at reference_speed_m_s: each planned yaw rate stays within
    `yaw_rate_trust(v)` of the linearization trajectory's (v its speed there), so the plan's
    headings stay where the linearized model holds [rad/s]."""
    seed_switch_ratio: float = 0.7
    """The linearization keeps following its previous plan unless another seed's rollout scores
    at most this fraction of the plan's (hysteresis against alternating seeds)."""
    target_lost_s: float = 2.0
    """No target observation for this long: the target is lost and its prediction flown on
    (`fleetmpc.onboard.core.target_watch`) [s]."""
    target_predict_s: float = 8.0
    """How long after its last observation a lost target's prediction is flown before the
    formation holds where it is [s]."""
    target_reacquire_s: float = 3.0
    """After a hold, the followed target glides to the new estimate over at least this long [s]."""
    solver_eps: float = 1e-6
    """OSQP eps_abs and eps_rel."""
    solver_max_iter: int = 4000
    """OSQP iteration limit per solve."""

    def __post_init__(self) -> None:
        positive("controller.period_s", self.period_s)
        if not isinstance(self.horizon, int) or not 1 <= self.horizon <= 100:
            raise ConfigError(
                "controller.horizon", f"must be an integer in [1, 100], got {self.horizon!r}"
            )
        for name in (
            "speed_max_m_s",
            "yaw_rate_max_rad_s",
            "q_position",
            "r_speed",
            "r_yaw_rate",
            "reference_speed_m_s",
            "min_linearization_speed_m_s",
            "plan_extrapolation_s",
            "plan_stale_s",
            "plan_forget_s",
            "yaw_rate_trust_rad_s",
            "speed_rate_max_m_s2",
            "target_lost_s",
            "target_predict_s",
            "target_reacquire_s",
        ):
            positive(f"controller.{name}", getattr(self, name))
        for name in (
            "q_heading",
            "q_formation",
            "w_position_m",
            "w_heading_rad",
            "d_safe_m",
            "r_yaw_rate_change",
            "silent_allowance_m",
        ):
            positive(f"controller.{name}", getattr(self, name), allow_zero=True)
        in_range("controller.solver_eps", self.solver_eps, 1e-12, 1e-5)
        in_range("controller.seed_switch_ratio", self.seed_switch_ratio, 0.0, 1.0)
        if not isinstance(self.neighbours_max, int) or self.neighbours_max < 1:
            raise ConfigError(
                "controller.neighbours_max",
                f"must be an integer >= 1, got {self.neighbours_max!r}",
            )
        if not isinstance(self.solver_max_iter, int) or self.solver_max_iter < 10:
            raise ConfigError(
                "controller.solver_max_iter",
                f"must be an integer >= 10, got {self.solver_max_iter!r}",
            )
        if self.min_linearization_speed_m_s > self.speed_max_m_s:
            raise ConfigError(
                "controller.min_linearization_speed_m_s", "must not exceed speed_max_m_s"
            )

    def yaw_rate_trust(self, speed_m_s: float) -> float:
        """The trust region's half-width about a yaw rate linearized at `speed_m_s` (> 0)
        [rad/s]: yaw_rate_trust_rad_s at the reference speed, times sqrt(reference speed /
        speed). The linearized model's position error from a heading dth off the
        linearization's grows as v dth^2, so a plan may turn as far from it at every speed
        for the same error: further when slow (docs/design.md, "Yaw-rate trust region")."""
        return self.yaw_rate_trust_rad_s * math.sqrt(self.reference_speed_m_s / speed_m_s)

    @property
    def period_ns(self) -> int:
        return round(self.period_s * 1e9)


@dataclass(frozen=True)
class LearningSettings:
    """Dual EKF settings (paper Sec. V-A, Wan & Nelson). Parameters beta = (a_V, a_w, d_x, d_y)."""

    enabled: bool = True
    """Learn beta online; when False, beta stays at its initial value (plain tube MPC)."""
    beta_initial: tuple[float, float, float, float] = (1.0, 1.0, 0.0, 0.0)
    """Initial speed effectiveness, yaw-rate effectiveness, drift North [m/s], drift East [m/s]."""
    beta_std_initial: tuple[float, float, float, float] = (0.2, 0.2, 0.5, 0.5)
    """Initial standard deviation of each parameter."""
    beta_random_walk: tuple[float, float, float, float] = (1e-3, 1e-3, 5e-3, 5e-3)
    """Random-walk standard deviation of each parameter per second (per sqrt(s)); the drift's
    is its slow mean's."""
    gust_std_m_s: float = 0.0
    """Standard deviation on each axis of the drift's fast part, a Gauss-Markov gust [m/s]
    (docs/design.md, "The wind's two parts"); 0: the drift is its mean alone."""
    gust_time_constant_s: float = 5.0
    """Time constant of that gust [s]."""
    fleet_wind: bool = True
    """Fuse the wind samples the neighbours broadcast with their plans into the drift
    (docs/design.md, "The fleet's wind")."""
    wind_length_m: float = 30.0
    """Distance over which two vehicles' gusts decorrelate [m] (the turbulence's length scale;
    a scenario's wind sets it); inf: the wind's changing part is the same everywhere."""
    beta_min: tuple[float, float, float, float] = (0.5, 0.5, -3.0, -3.0)
    """Lower bound of each parameter."""
    beta_max: tuple[float, float, float, float] = (1.5, 1.5, 3.0, 3.0)
    """Upper bound of each parameter."""
    process_position_std_m: float = 0.005
    """State-filter process noise on position per control period, learned model [m]."""
    process_heading_std_rad: float = 0.003
    """State-filter process noise on heading per control period, learned model [rad]."""
    fixed_model_position_std_m: float = 0.05
    """State-filter process noise on position when learning is off [m]: a fixed nominal model is
    trusted less, so the no-learning baseline's error is the controller's, not estimator lag."""
    fixed_model_heading_std_rad: float = 0.01
    """State-filter process noise on heading when learning is off [rad]."""
    measurement_position_std_m: float = 0.05
    """Assumed standard deviation of position measurements [m]."""
    measurement_heading_std_rad: float = 0.01
    """Assumed standard deviation of heading measurements [rad]."""
    measurement_velocity_std_m_s: float = 0.05
    """Assumed standard deviation of each ground-velocity component the autopilot reports
    [m/s]: its estimator's, GNSS-aided and smoothed by the inertial sensors."""
    excitation_min: tuple[float, float, float, float] = (0.05, 0.01, 0.0, 0.0)
    """Smallest |dstate/dbeta_i| / tau that lets beta_i update (a Schmidt "consider" update holds
    the others): with |V| below 0.05 m/s a_V is not learned, with |omega| below 0.01 rad/s a_w."""
    innovation_gate: float = 50.0
    """Normalized innovation (in standard deviations) above which the filter resets."""
    input_lag_s: float = 0.1
    """Time constant of the autopilot's first-order response to a setpoint [s]: the DEKF
    predicts with the input as the vehicle flew it over the period (docs/design.md,
    "Learning"); 0: each setpoint is flown at once."""
    speed_excitation_m_s: float = 0.2
    """a_V is learned only while the commanded velocity's mean over the last second stands this
    far from its mean over the last VELOCITY_SLOW_S seconds [m/s]: a wind moves the vehicle as
    a_V would, and only a change of the command that the wind does not share tells them
    apart."""

    def __post_init__(self) -> None:
        for name in (
            "beta_initial",
            "beta_std_initial",
            "beta_random_walk",
            "beta_min",
            "beta_max",
            "excitation_min",
        ):
            object.__setattr__(self, name, vector(f"learning.{name}", getattr(self, name), 4))
        for i in range(4):
            if not self.beta_min[i] <= self.beta_initial[i] <= self.beta_max[i]:
                raise ConfigError(
                    f"learning.beta_initial[{i}]", "must lie within beta_min and beta_max"
                )
            positive(f"learning.beta_std_initial[{i}]", self.beta_std_initial[i])
            positive(f"learning.beta_random_walk[{i}]", self.beta_random_walk[i], allow_zero=True)
            positive(f"learning.excitation_min[{i}]", self.excitation_min[i], allow_zero=True)
        if self.beta_min[0] <= 0 or self.beta_min[1] <= 0:
            raise ConfigError("learning.beta_min", "effectiveness bounds must be > 0")
        for name in (
            "process_position_std_m",
            "process_heading_std_rad",
            "fixed_model_position_std_m",
            "fixed_model_heading_std_rad",
            "measurement_position_std_m",
            "measurement_heading_std_rad",
            "measurement_velocity_std_m_s",
            "innovation_gate",
        ):
            positive(f"learning.{name}", getattr(self, name))
        positive("learning.gust_time_constant_s", self.gust_time_constant_s)
        length = self.wind_length_m
        if isinstance(length, bool) or not (isinstance(length, int | float) and length > 0.0):
            raise ConfigError(
                "learning.wind_length_m", f"must be > 0 (inf allowed), got {self.wind_length_m!r}"
            )
        if not isinstance(self.fleet_wind, bool):
            raise ConfigError(
                "learning.fleet_wind", f"must be true or false, got {self.fleet_wind!r}"
            )
        for name in ("input_lag_s", "speed_excitation_m_s", "gust_std_m_s"):
            positive(f"learning.{name}", getattr(self, name), allow_zero=True)


_FRAMES = ("world", "course")


@dataclass(frozen=True)
class FormationSettings:
    """Formation geometry: slots around a centre that trails the target along its course."""

    slots_m: tuple[tuple[float, float], ...]
    """Offset of each vehicle's slot from the formation centre (index = vehicle order) [m]."""
    frame: str = "world"
    """"world": offsets are (North, East); "course": (forward, right) in the target's course
    frame."""
    trail_m: float = 5.0
    """Distance d_s by which the formation centre trails the target along its course [m]."""
    neighbours: int = 8
    """The formation graph: each slot is linked to this many nearest slots (all of them in a
    formation of at most this many and one); a vehicle's cost holds a formation term for each
    slot its own is linked to."""

    def __post_init__(self) -> None:
        if self.frame not in _FRAMES:
            raise ConfigError("formation.frame", f"must be one of {_FRAMES}, got {self.frame!r}")
        slots = tuple(vector(f"formation.slots_m[{i}]", s, 2) for i, s in enumerate(self.slots_m))
        if not slots:
            raise ConfigError("formation.slots_m", "needs at least one slot")
        object.__setattr__(self, "slots_m", slots)
        finite("formation.trail_m", self.trail_m)
        if not isinstance(self.neighbours, int) or self.neighbours < 1:
            raise ConfigError(
                "formation.neighbours", f"must be an integer >= 1, got {self.neighbours!r}"
            )
