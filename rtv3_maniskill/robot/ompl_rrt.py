"""Joint-space RRTConnect with OMPL: a collision-free path of the Panda's arm to any of several goals.

Joint vectors are ``(7,)`` arm joints in radians. Motions are checked every ``resolution`` rad
(joint-space L2, OMPL's ``setStateValidityCheckingResolution`` as a fraction of the space's
extent) with the caller's state validity test; the found path is shortcut by OMPL's
simplifier. Planning is reproducible per ``seed``.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import ompl.base as ob
import ompl.geometric as og
import ompl.util as ou

from rtv3_maniskill.robot.panda_model import DOF

ou.setLogLevel(ou.LogLevel.LOG_WARN)


def seed_ompl(seed: int) -> None:
    """Seed OMPL's RNG seed generator (``ompl.util.RNG.setSeed``).

    OMPL logs an error when the seed changes after random numbers were drawn; the
    reseed still applies to every RNG created afterwards, and a plan creates fresh
    planners and samplers, so planning is reproducible per seed. The log is muted.
    """
    level = ou.getLogLevel()
    ou.setLogLevel(ou.LogLevel.LOG_NONE)
    try:
        ou.RNG.setSeed(int(seed) % (2**31 - 2) + 1)  # OMPL rejects 0
    finally:
        ou.setLogLevel(level)


def rrt_connect(
    q_start: np.ndarray,
    goals: np.ndarray,
    time_left: float,
    seed: int,
    lower: np.ndarray,
    upper: np.ndarray,
    is_valid: Callable[[np.ndarray], bool],
    resolution: float,
    simplify_time: float,
) -> tuple[np.ndarray | None, str]:
    """RRTConnect from ``q_start (7,)`` to any of ``goals (G, 7)`` within ``time_left`` s, then simplified.

    ``lower``/``upper`` ``(7,)``: the state space's bounds (rad); ``is_valid(q)``: whether a
    ``(7,)`` state is collision-free (called in OMPL's hot loop with one reused buffer);
    ``resolution``: motion checking step (rad); ``simplify_time``: OMPL's simplification
    budget (s). Returns ``(path (K, 7) or None, status)``, status ``"timeout"`` when no path
    was found in time, else OMPL's status text; repeated states are dropped from the path.
    """
    if time_left <= 0:
        return None, "timeout"
    seed_ompl(seed)
    space = ob.RealVectorStateSpace(DOF)
    bounds = ob.RealVectorBounds(DOF)
    for i in range(DOF):
        bounds.setLow(i, float(lower[i]))
        bounds.setHigh(i, float(upper[i]))
    space.setBounds(bounds)
    ss = og.SimpleSetup(space)
    buf = np.zeros(DOF)

    def valid(state) -> bool:
        for i in range(DOF):
            buf[i] = state[i]
        return is_valid(buf)

    ss.setStateValidityChecker(valid)
    si = ss.getSpaceInformation()
    si.setStateValidityCheckingResolution(resolution / space.getMaximumExtent())

    def to_state(q):
        s = space.allocState()
        for i in range(DOF):
            s[i] = float(q[i])
        return s

    ss.setStartState(to_state(q_start))
    goal = ob.GoalStates(si)
    for g in goals:
        goal.addState(to_state(g))
    ss.setGoal(goal)
    ss.setPlanner(og.RRTConnect(si))
    status = ss.solve(float(time_left))
    name = str(status)
    if not ss.haveExactSolutionPath():
        return None, "timeout" if status.getStatus() == ob.PlannerStatus.TIMEOUT else name
    ss.simplifySolution(simplify_time)
    path = ss.getSolutionPath()
    out = np.array([[path.getState(k)[i] for i in range(DOF)] for k in range(path.getStateCount())])
    # Drop repeated states (zero-length segments break the arc-length spline).
    keep = [0] + [k for k in range(1, len(out)) if np.linalg.norm(out[k] - out[k - 1]) > 1e-9]
    return out[keep], name
