#!/usr/bin/env python3
"""Replay `hil tune`'s pruning rule on a study run without it: which trials it would have stopped, and whether the
study's winner is among them.

    .venv/bin/python benchmarks/prune_replay.py --campaign CAMPAIGN.yaml --storage sqlite:///OUT/tune.db [--study NAME]
        [--controller LABEL]

Run the study first with ``hil tune ... --no-prune`` (every trial runs every cell; each trial keeps its cells'
objective values). Then, for each trial in the order it started, the rule (``hil.tune.CellPruner``, the object
`hil tune` uses) is asked after each of its cells but the last, against the trials that had completed when it
started. The winner is the best complete feasible trial of the study. Prints how many trials would have stopped
and after how many cells, the cells that saves, and the winner's fate.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import optuna
from optuna.trial import TrialState, create_trial

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from hil.campaign import load_campaign
from hil.tune import CellPruner, choose_controller, trial_campaign


def running_means(values: list[float]) -> dict[int, float]:
    return {k: sum(values[:k + 1]) / (k + 1) for k in range(len(values))}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--campaign", type=Path, required=True)
    ap.add_argument("--storage", required=True, help="the study's SQLAlchemy URL")
    ap.add_argument("--study", default=None, help="default: the campaign's name")
    ap.add_argument("--controller", default=None)
    args = ap.parse_args()
    optuna.logging.set_verbosity(optuna.logging.WARNING)  # one in-memory study per trial replayed
    config = load_campaign(args.campaign)
    entry = choose_controller(config, args.controller)
    study = optuna.load_study(study_name=args.study or config.name, storage=args.storage)
    goal = str(study.user_attrs.get("objective", ""))
    cells = [s for s in trial_campaign(config, entry, {}).cells()
             if "@" not in goal or s.profile.label.startswith(goal.split("@", 1)[1].rstrip("*"))]
    ids = [s.cell_id for s in cells]
    done = [t for t in study.get_trials(deepcopy=False) if t.state == TrialState.COMPLETE]
    feasible = [t for t in done if all(c <= 0 for c in t.constraints.values())]
    sign = 1.0 if study.direction == optuna.study.StudyDirection.MINIMIZE else -1.0
    winner = min(feasible, key=lambda t: (sign * t.value, t.number))
    pruner = CellPruner()
    stopped: dict[int, int] = {}  # trial -> cells it would have run
    for t in sorted(done, key=lambda t: (t.datetime_start, t.number)):
        values = [float(t.user_attrs["cells"][i]) for i in ids]
        before = optuna.create_study(direction=study.direction)
        for u in done:
            if u.datetime_complete is not None and t.datetime_start is not None \
                    and u.datetime_complete <= t.datetime_start:
                before.add_trial(create_trial(
                    value=u.value, intermediate_values=running_means([float(u.user_attrs["cells"][i]) for i in ids]),
                    constraints=dict(u.constraints) or None))
        for step in range(len(values) - 1):
            probe = create_trial(state=TrialState.RUNNING,
                                 intermediate_values={k: v for k, v in running_means(values).items() if k <= step})
            if pruner.prune(before, probe):
                stopped[t.number] = step + 1
                break
    saved = sum(len(ids) - n for n in stopped.values())
    print(f"study {study.study_name}: {len(done)} complete trials of {len(ids)} cells each; the rule (margin "
          f"{100 * pruner.margin:.0f} %, after {pruner.startup_trials} complete trials) would have stopped "
          f"{len(stopped)} of them, saving {saved} of {len(done) * len(ids)} cells "
          f"({100 * saved / max(1, len(done) * len(ids)):.0f} %)")
    print(f"winner: trial {winner.number}, {goal} {winner.value:.5g}: "
          + ("would have been STOPPED" if winner.number in stopped else "never stopped"))
    top = sorted(feasible, key=lambda t: sign * t.value)[:10]
    print("the 10 best: " + ", ".join(f"{t.number}{' (stopped)' if t.number in stopped else ''}" for t in top))
    return 1 if winner.number in stopped else 0


if __name__ == "__main__":
    raise SystemExit(main())
