"""Tune a controller with `hil tune` and measure what the tuning bought (docs/tuning.md).

    .venv/bin/python benchmarks/bench_tune.py [--campaign profiles/campaigns/tune-eso-kf-miss-3deg.yaml]
        [--controller ESO+KF] [--params "..."] [--trials 200] [--workers 2] [--skip-tune] [--json PATH]
        [--also LABEL ...] [--show METRIC] [--oracle ORACLE.yaml | --oracle-trials N]

1. The study: ``hil.tune.tune`` on the campaign (its cells, the tuned controller's entry), ``--trials`` trials,
   ``--workers`` at a time; its wall time is printed.
2. The comparison: one campaign with the baseline (the campaign's ``baseline``), the tuned entry with its
   campaign parameters (the paper's defaults), the same entry with the tuned parameters, and the ``oracle``
   controller (the plant's true rate, sim clock only; left out if the registry has none) on the campaign's own
   cells (the seeds the study saw) and on held-out cells (other seeds, longer cells: ``--heldout-seeds``,
   ``--heldout-duration``). For each: the objective's mean over the cells and the fraction of the
   baseline-to-oracle gap it closes, ``(baseline - x) / (baseline - oracle)``. The oracle runs with the registry's
   gains, or with its own tuned ones (``--oracle YAML``, or ``--oracle-trials N``: a study of its kp and ki on the
   same cells first), so that the gap is measured to the best this loop could do on that plant.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from hil.campaign import load_campaign  # noqa: E402
from hil.campaign.model import ControllerEntry  # noqa: E402
from hil.config import ControllerConfig, load_model  # noqa: E402
from hil.tune import choose_controller, compare_controllers, tune  # noqa: E402

SPACE = "omega_o_rad_s=100..2000:log, kp_counts_per_dps=1000..20000:log, q_dps2=1e-6..1e-2:log"
ORACLE_SPACE = "kp_counts_per_dps=300..40000:log, ki_counts_per_deg=1..1000000:log"  # kp k_m dt < 1, ki dt <= kp


def tune_oracle(config, objective: str, trials: int, *, workers: int, out: Path, resume: bool,
                seed: int) -> Path | None:
    """The oracle's own gains tuned on the campaign's cells (its default kp can ring a plant's mode or sit far from
    its best): a study of ``trials`` trials over ORACLE_SPACE; returns its controller YAML."""
    base = next(c for c in config.controllers if c.label == config.baseline)
    cfg = config.model_copy(update={"controllers": [base, ControllerEntry(label="oracle", name="oracle")],
                                    "name": f"{config.name}-oracle", "acceptance": [], "paper": {}})
    t0 = time.perf_counter()
    result = tune(cfg, ORACLE_SPACE, objective=objective, trials=trials, controller="oracle", workers=workers,
                  out=out, resume=resume, seed=seed, heldout_seeds=0)
    wall = time.perf_counter() - t0
    print(f"oracle study {result.study}: {result.trials_run} trials run, {wall:.0f} s wall; {result.n_complete} "
          f"complete, {result.n_failed} failed; best trial {result.best_trial}: {objective} {result.best_value}: "
          f"{result.best_params}")
    return result.yaml_path


def compare(config, entry, tuned_params, objective: str, *, jobs: int, seeds: list[int] | None,
            duration_s: float | None, also: list[str] = (), show: str | None = None,
            oracle_params: dict | None = None) -> dict[str, dict[str, float]]:
    """The objective's mean (and per-cell values) for baseline, the campaign's entries ``also``, default, tuned and
    oracle (with ``oracle_params``: its own tuned gains) on one set of cells (:func:`hil.tune.compare_controllers`,
    the comparison a study's report makes on held-out seeds); ``show``: a second metric's mean beside it."""
    numbers = compare_controllers(config, entry, tuned_params, [objective, "drive_ripple_el_counts",
                                                                 *([show] if show else [])],
                                  seeds=seeds, duration_s=duration_s, jobs=jobs, also=also,
                                  oracle_params=oracle_params)
    for label, n in numbers.items():
        if not label.startswith("_"):
            n["ripple"] = n["means"]["drive_ripple_el_counts"]
            if show:
                n["show"] = n["means"][show]
    return numbers


def _mean(v: list[float]) -> float:
    return sum(v) / len(v) if v else math.nan


def table(title: str, numbers: dict[str, dict[str, float]], baseline: str, objective: str,
          show: str | None = None) -> list[str]:
    ref = numbers[baseline]["mean"]
    oracle = numbers.get("oracle", {}).get("mean", math.nan)
    extra = f" {show}, mean |" if show else ""
    lines = [f"{title} ({numbers['_wall_s']['mean']:.0f} s wall)", "",
             f"| controller | {objective}, mean | per cell |{extra} drive ripple el (counts) | gap closed |",
             f"|---|---:|---|{'---:|' if show else ''}---:|---:|"]
    for label, n in numbers.items():
        if label.startswith("_"):
            continue
        gap = (ref - n["mean"]) / (ref - oracle) if math.isfinite(oracle) and ref != oracle else math.nan
        cells = ", ".join(f"{x:.4g}" for x in n["values"])
        shown = f" {n.get('show', math.nan):.4g} |" if show else ""
        lines.append(f"| {label} | {n['mean']:.4g} | {cells} |{shown} {n['ripple']:.0f} | "
                     f"{'n/a' if not math.isfinite(gap) else f'{100 * gap:.0f} %'} |")
    return lines


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--campaign", type=Path, default=ROOT / "profiles" / "campaigns" / "tune-eso-kf-miss-3deg.yaml")
    ap.add_argument("--controller", default=None)
    ap.add_argument("--params", default=SPACE)
    ap.add_argument("--objective", default="miss_std_px")
    ap.add_argument("--constraint", action="append", default=[])
    ap.add_argument("--trials", type=int, default=200)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--study", default=None)
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--resume", action="store_true")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--skip-tune", action="store_true", help="use the tuned YAML already in --out")
    ap.add_argument("--write-profile", type=Path, default=None)
    ap.add_argument("--heldout-seeds", type=int, nargs="*", default=[3, 4, 5])
    ap.add_argument("--heldout-duration", type=float, default=20.0)
    ap.add_argument("--jobs", type=int, default=2, help="cells at once in the comparison campaigns")
    ap.add_argument("--also", action="append", default=[],
                    help="another controller label of the campaign to compare (repeatable)")
    ap.add_argument("--show", default=None, help="a second metric shown beside the objective")
    ap.add_argument("--oracle", type=Path, default=None,
                    help="the oracle's controller YAML (its gains tuned on the same cells: hil tune --controller "
                         "oracle); default: the registry's")
    ap.add_argument("--oracle-trials", type=int, default=0,
                    help="first tune the oracle's kp and ki on the campaign's cells (a study of this many trials in "
                         "OUT/oracle, resumed if there) and compare against that oracle")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()

    config = load_campaign(args.campaign)
    entry = choose_controller(config, args.controller)
    out = args.out or ROOT / "runs" / "tune" / (args.study or config.name)
    report: dict[str, object] = {"campaign": str(args.campaign), "controller": entry.label}
    if not args.skip_tune:
        t0 = time.perf_counter()
        result = tune(config, args.params, objective=args.objective, trials=args.trials, controller=entry.label,
                      constraints=args.constraint, workers=args.workers, study=args.study, resume=args.resume,
                      out=out, seed=args.seed, write_profile=args.write_profile,
                      heldout_seeds=0)  # the comparison below is this benchmark's own
        wall = time.perf_counter() - t0
        print(f"study {result.study}: {result.trials_run} trials run ({len(result.trials)} in the study), "
              f"{args.workers} workers: {wall:.0f} s wall ({wall / max(result.trials_run, 1):.1f} s per trial); "
              f"{result.n_complete} complete, {result.n_infeasible} infeasible, {result.n_failed} failed")
        print(f"best trial {result.best_trial}: {args.objective} {result.best_value}: {result.best_params}")
        report.update(study_wall_s=wall, trials_run=result.trials_run, trials=len(result.trials),
                      failed=result.n_failed, infeasible=result.n_infeasible, best_trial=result.best_trial,
                      best_value=result.best_value, best_params=result.best_params)
        yaml_path = result.yaml_path
    else:
        yaml_path = out / f"{entry.name}-tuned.yaml"
    if yaml_path is None or not yaml_path.exists():
        print("no tuned controller: nothing to compare")
        return
    tuned = load_model(ControllerConfig, yaml_path).params
    baseline = config.baseline or config.controllers[0].label
    oracle_params = None
    oracle_yaml = args.oracle
    if args.oracle_trials:
        oracle_yaml = tune_oracle(config, args.objective, args.oracle_trials, workers=args.workers,
                                  out=out / "oracle", resume=(out / "oracle" / "tune.db").exists(), seed=args.seed)
    if oracle_yaml is not None:
        oracle = load_model(ControllerConfig, oracle_yaml)
        if oracle.name != "oracle":
            raise SystemExit(f"--oracle {oracle_yaml}: a controller file of 'oracle', not {oracle.name!r}")
        oracle_params = oracle.params
        report["oracle_params"] = oracle_params
    lines = []
    for title, seeds, duration in (
            (f"the study's cells ({config.duration_s:g} s, seeds {config.seeds})", None, None),
            (f"held-out cells ({args.heldout_duration:g} s, seeds {args.heldout_seeds})", args.heldout_seeds,
             args.heldout_duration)):
        if seeds == []:
            continue
        numbers = compare(config, entry, tuned, args.objective, jobs=args.jobs, seeds=seeds, duration_s=duration,
                          also=args.also, show=args.show, oracle_params=oracle_params)
        report[title] = numbers
        lines += [*table(title, numbers, baseline, args.objective, args.show), ""]
    print("\n".join(lines))
    if args.json is not None:
        args.json.write_text(json.dumps(report, indent=2, default=str))


if __name__ == "__main__":
    main()
