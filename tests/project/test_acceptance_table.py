"""The committor tilt's acceptance table (``benchmarks/default_runs.py --acceptance``): each target judged from the
parts' numbers, on hand-made runs whose figures are computed here by hand."""

import math

import numpy as np
import pytest

from conftest import REPO, load_script

study = load_script(REPO / "benchmarks" / "default_runs.py")


def runs(ratios, holds, truth=-9.0, sims=None, verdicts=None, half=0.2):
    """Hand-made runs of one setting (:func:`scenario_runs`' dictionary): estimates ``ratios`` x exp(truth), each
    interval +-``half`` in logs (``truth`` nan: a setting without a reference, estimates exp(-20) x ``ratios``)."""
    ratios = np.asarray(ratios, dtype=float)
    logs = (-20.0 if math.isnan(truth) else truth) + np.log(ratios)  # no reference: the ratios are nan
    return {
        "truth": truth,
        "logs": logs,
        "cis": [(x - half, x + half) for x in logs],
        "ratios": ratios * (math.nan if math.isnan(truth) else 1.0),
        "holds": np.asarray(holds, dtype=bool),
        "verdicts": verdicts or ["doubtful"] * ratios.size,
        "sims": np.asarray(sims if sims is not None else [12995] + [11530] * (ratios.size - 1)),
        "walls": np.ones(ratios.size),
    }


def parts(**over):
    """Every part's numbers with every target met, ``over`` replacing some."""
    base = {
        "cut-in": runs([0.9, 1.1] * 10, [True] * 20),
        "cut-in wall": 22.0,
        "rare tilt": runs([1.0, 1.5] * 5, [True] * 10, truth=math.nan, half=0.4),
        "rare ams 0-4": runs([1.1, 1.4] * 2 + [1.0], [True] * 5, truth=math.nan, half=0.4),
        "rare ams 5-9": runs([1.5] + [1.1, 1.4] * 2, [True] * 5, truth=math.nan, half=0.4),
        "braking": runs(
            [0.99, 1.01] * 100, [True] * 200, truth=math.log(1.984e-15), sims=[2100] * 200, verdicts=["reliable"] * 200
        ),
        "braking committor": {
            "log10_v_median": -0.5,
            "log10_v_rms": 0.6,
            "shift_rms": 0.8,
            "mean": 1.0,
            "relvar_sims_solving": 0.4,
            "relvar_sims_reusing": 0.3,
        },
        "paper": math.log(5.6372e-19),
        "toy": {"mean": 1.004, "se": 0.007},
    }
    return {**base, **over}


def judged(rows):
    return {target.strip(): (figure, met) for target, figure, met in rows}


def test_every_target_met_reads_yes_with_the_figures_computed_by_hand():
    rows = judged(study.acceptance_rows(parts()))
    assert rows["cut-in, default command, 20 seeds: median relative error <= 0.2"] == ("0.100", True)
    assert rows["the reference inside the 95 % interval in >= 18 of 20"] == ("20 of 20", True)
    assert rows["no run off by more than x2"] == ("0 beyond (x0.90 to x1.10)", True)
    cost = "cost <= 13,000 rollout-equivalents (first run; a run reusing the proposal)"
    assert rows[cost] == ("12,995; 11,530", True)
    lt, la = np.log([1.0, 1.5] * 5), np.log([1.1, 1.4] * 4 + [1.0, 1.5])  # the two estimators' logs less -20
    se = math.sqrt(lt.var(ddof=1) / 10 + la.var(ddof=1) / 10)
    diff = lt.mean() - la.mean()
    assert rows["cut-in rare, tilt and splitting, 10 seeds: every seed's two intervals overlap"] == (
        f"10 of 10; geometric means x{math.exp(diff):.2f} apart ({abs(diff) / se:.1f} SE)",
        True,
    )
    # sd of logs of [1, 1.5] x 5 = ln 1.5 / 2 x sqrt(10 / 9) = 0.2137 against the intervals' +-0.4 / 1.96 = 0.204
    assert rows["tilt: the seeds' spread matches the intervals (sd of logs / interval sd in 2/3..3/2)"] == (
        "0.21 / 0.20",
        True,
    )
    # splitting: the same intervals, logs of 1.0, 1.1 x 4, 1.4 x 4, 1.5
    sd = np.std(np.log([1.0, 1.5] + [1.1] * 4 + [1.4] * 4), ddof=1)
    assert rows["splitting: the seeds' spread matches the intervals (sd of logs / interval sd in 2/3..3/2)"] == (
        f"{sd:.2f} / 0.20",
        True,
    )
    assert rows["braking, default command, 200 seeds: median relative error <= 0.021"] == ("0.0100", True)
    assert rows["the exact answer inside the interval in >= 95 %"] == ("200 of 200", True)
    # relvar of [0.99, 1.01] x 100 = 0.01^2 x 200 / 199, times 2,100 simulations
    assert rows["relvar x simulations of the default (printed)"] == (f"{1e-4 * 200 / 199 * 2100:.2f}", None)
    assert rows["the authors'-settings preset, seed 0, gives 5.6372e-19"] == ("5.6372e-19", True)
    assert rows["every verdict honest: no 'reliable' beyond x2, no nan (240 runs)"] == (
        "0 wrong 'reliable', 0 nan",
        True,
    )
    assert rows["the tilt on the toy with a poor committor is unbiased (mean within 3 standard errors of p)"][1] is True


@pytest.mark.parametrize(
    ("over", "target", "figure"),
    [
        (
            {"cut-in": runs([0.9, 1.1] * 10, [True] * 17 + [False] * 3)},
            "the reference inside the 95 % interval in >= 18 " "of 20",
            "17 of 20",
        ),
        (
            {"cut-in": runs([0.9, 1.1] * 9 + [0.45, 1.0], [True] * 20)},
            "no run off by more than x2",
            "1 beyond (x0.45 to x1.10)",
        ),
        (
            {"rare tilt": runs([1.0, 3.0] * 5, [True] * 10, truth=math.nan, half=0.4)},
            "tilt: the seeds' spread matches " "the intervals (sd of logs / interval sd in 2/3..3/2)",
            "0.58 / 0.20",
        ),
        ({"cut-in wall": 31.0}, "wall time <= 30 s (the command with its recording, a fresh process)", "31.0 s"),
        ({"paper": math.log(1.2264e-24)}, "the authors'-settings preset, seed 0, gives 5.6372e-19", "1.2264e-24"),
        (
            {
                "braking": runs(
                    [0.99, 1.01] * 99 + [2.5, 1.0],
                    [True] * 200,
                    truth=math.log(1.984e-15),
                    sims=[2100] * 200,
                    verdicts=["reliable"] * 200,
                )
            },
            "every verdict honest: no 'reliable' beyond x2, no nan (240 runs)",
            "1 wrong 'reliable', 0 nan",
        ),
        (
            {"toy": {"mean": 1.03, "se": 0.007}},
            "the tilt on the toy with a poor committor is unbiased (mean within 3 " "standard errors of p)",
            "x1.0300 (standard error 0.0070)",
        ),
    ],
)
def test_a_target_missed_reads_no_with_its_figure(over, target, figure):
    rows = judged(study.acceptance_rows(parts(**over)))
    assert rows[target] == (figure, False)


def test_splitting_ten_times_higher_on_half_the_seeds_leaves_those_intervals_apart():
    # the first 5 seeds of splitting x10 (logs 2.30 higher), every interval +-0.4: those 5 cannot overlap the tilt's
    rows = judged(
        study.acceptance_rows(
            parts(**{"rare ams 0-4": runs([11.0, 14.0, 11.0, 14.0, 10.0], [True] * 5, truth=math.nan, half=0.4)})
        )
    )
    figure, met = rows["cut-in rare, tilt and splitting, 10 seeds: every seed's two intervals overlap"]
    assert met is False and figure.startswith("5 of 10; ")
