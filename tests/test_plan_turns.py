"""plan_tables' plans over several coordinates run in turns (planner._plan_in_turns): a plan is
dropped only when it is far behind another, a plan that reached its targets stops the others
where they have as many cells, and the result keeps the candidates' order. Fake plans (the
generator protocol of plan_tables' `plan`): no material, no tables."""
import numpy as np

from bake.core import planner


def fake_plan(trajectories, finals, seen):
    """plan(coords, say, beat) yielding (bins, cells, typical) per round from `trajectories`, then
    returning a result tuple whose (worst, excess) is finals[coords]; stops ("stopped", excess inf)
    when beat["cells"] is reached, as plan_tables' plan does. seen[coords]: the rounds it ran."""
    def plan(coords, say, beat):
        seen[coords] = 0
        cells = 0
        for k, typical in enumerate(trajectories[coords]):
            cells = (12 + k) * 100
            seen[coords] += 1
            yield 12 + k, cells, typical
            if beat["cells"] is not None and cells >= beat["cells"]:
                say(f"bins {12 + k}: stopped")
                return 10, list(range(12 + k)), None, 0.0, (np.inf, np.inf), None
        return 10, list(range(12 + len(trajectories[coords]) - 1)), None, 0.0, finals[coords], None
    return plan


def test_a_plan_far_behind_is_dropped_after_three_rounds():
    seen, lines = {}, []
    traj = {"wo": [35.0, 25.0, 18.9, 13.5, 9.4, 6.9, 4.9, 3.5, 2.7, 2.5],    # satin_rosaline-like
            "halfpolar": [7.0, 5.0, 3.96, 2.2, 1.9, 1.6, 1.4, 1.2, 1.1, 1.09]}
    finals = {"wo": (3.3, 1.45), "halfpolar": (1.8, 1.09)}
    plans = planner._plan_in_turns(["wo", "halfpolar"], fake_plan(traj, finals, seen), lines.append)
    assert list(plans) == ["halfpolar"] and seen == {"wo": 3, "halfpolar": len(traj["halfpolar"])}, (plans, seen)
    assert any(line.startswith("wo: bins 14: dropped") for line in lines), lines


def test_a_plan_that_catches_up_is_kept():
    """ilm_solo_m_68's measured trajectories (wo over halfpolar 6.0x at round 1, then 2.1-3.0x):
    its wo plan ends closer to its targets and must run to its end."""
    seen, lines = {}, []
    traj = {"wo": [38.2, 18.3, 12.7, 10.2, 9.1, 8.2, 7.7, 4.3, 3.5, 2.3, 1.9, 1.5, 1.2, 1.05, 1.02],
            "halfpolar": [6.3, 5.6, 5.0, 4.6, 4.3, 3.6, 3.5, 1.44, 1.40, 1.09, 1.07]}
    finals = {"wo": (1.55, 1.02), "halfpolar": (1.47, 1.07)}
    plans = planner._plan_in_turns(["wo", "halfpolar"], fake_plan(traj, finals, seen), lines.append)
    assert list(plans) == ["wo", "halfpolar"] and seen == {c: len(t) for c, t in traj.items()}, (seen, lines)
    assert not any("dropped" in line for line in lines)


def test_a_plan_within_its_targets_stops_the_others_at_its_cells():
    """Whichever ends first within its targets (typical excess 1, the least there is) stops the
    other where it has as many cells and still splits; the result keeps the candidates' order."""
    seen, lines = {}, []
    traj = {"wo": [3.0, 2.5, 2.2, 2.0, 1.9, 1.8, 1.7, 1.6], "halfpolar": [2.0, 1.5, 1.0]}
    plans = planner._plan_in_turns(["wo", "halfpolar"],
                                    fake_plan(traj, {"wo": (2.0, 1.2), "halfpolar": (0.9, 1.0)}, seen), lines.append)
    assert list(plans) == ["wo", "halfpolar"], plans
    # halfpolar ends (14 bins) as wo yields its 15-bin round: wo stops there, the next one it looks
    assert plans["wo"][4] == (np.inf, np.inf) and seen["wo"] == 4, (seen, lines)
    assert any(line.startswith("wo: bins 15: stopped") for line in lines), lines


def test_one_candidate_runs_alone_and_logs_plainly():
    seen, lines = {}, []
    plan = fake_plan({None: [5.0, 50.0, 500.0]}, {None: (3.0, 2.0)}, seen)
    plans = planner._plan_in_turns([None], plan, lines.append)
    assert list(plans) == [None] and seen[None] == 3 and plans[None][4] == (3.0, 2.0) and not lines
