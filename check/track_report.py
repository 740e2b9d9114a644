"""What `fleetmpc check` says of a recorded track: the speeds, turn rates and gaps it holds, and
whether the formation can follow them (its speed bound, its reference course's turn-rate limit
in a course-frame formation, and how the agents ride out each gap: the prediction flown for
`controller.target_predict_s`, then the formation held)."""

from fleetmpc.onboard.core.formation import CourseRateLimit
from fleetmpc.scenario import Scenario
from fleetmpc.targets.track import RecordedTrack, track_stats

__all__ = ["track_lines"]


def track_lines(
    sc: Scenario, track: RecordedTrack, *, speed_bound_m_s: float, course_limit: CourseRateLimit
) -> tuple[list[str], list[str]]:
    """(report lines, problems) for a scenario whose target is a recorded track."""
    c = sc.controller
    st = track_stats(track)
    lines = [
        f"recorded track {track.file}: {st.fixes} fixes over {st.duration_s:.1f} s at "
        f"{st.rate_hz:.2f} Hz, noise {track.observation_noise_m:.2f} m",
        f"track speed: up to {st.speed_max_m_s:.2f} m/s (95 % below {st.speed_p95_m_s:.2f} m/s)",
        f"track turn rate: up to {st.turn_rate_max_rad_s:.3f} rad/s (95 % below "
        f"{st.turn_rate_p95_rad_s:.3f} rad/s) while moving",
    ]
    problems = []
    if st.speed_max_m_s > speed_bound_m_s:
        problems.append(
            f"the track reaches {st.speed_max_m_s:.2f} m/s, beyond the tightened speed bound "
            f"{speed_bound_m_s:.2f} m/s"
        )
    if sc.formation.frame == "course":
        limit = course_limit.at(st.speed_p95_m_s)
        if st.turn_rate_p95_rad_s > limit:
            lines.append(
                f"the track turns faster than the formation's course may ({limit:.3f} rad/s at "
                f"{st.speed_p95_m_s:.2f} m/s): its course lags the track's in the turns"
            )
    if not st.gaps:
        lines.append("track gaps: none")
    for start_s, length_s in st.gaps:
        if length_s <= c.target_lost_s:
            how = "within controller.target_lost_s: followed as ever"
        elif length_s <= c.target_predict_s:
            how = "the prediction flown through it"
        else:
            how = (
                f"the prediction flown {c.target_predict_s:g} s, then the formation holds for "
                f"{length_s - c.target_predict_s:.1f} s and glides back"
            )
        lines.append(f"track gap at t = {start_s:.1f} s for {length_s:.1f} s: {how}")
    return lines, problems
