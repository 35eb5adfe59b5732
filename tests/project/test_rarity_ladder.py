"""benchmarks/rarity_ladder.py: its rungs are valid ``--param`` settings of their registered scenes, each reference's
interval holds its point estimate and sits in the rung's decade, and the table's figures are those of the runs (no
engine run: seconds)."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import pytest
from pemviz.core.confidence import clopper_pearson
from pemviz.scenarios.parameters import apply_parameters, parse_assignments

from conftest import load_script

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def ladder():
    yield load_script(ROOT / "benchmarks" / "rarity_ladder.py")
    del sys.modules["rarity_ladder"]


def test_every_rung_is_a_valid_param_setting_of_its_scene(ladder):
    for r in ladder.RUNGS:
        pairs = parse_assignments(r.scene, r.params)
        params = apply_parameters(r.scene, dict(pairs))
        for name, value in pairs:
            assert getattr(params, name) == value, r.name
        assert r.flags == tuple(f for p in r.params for f in ("--param", p))
        assert r.command == f"pemviz run --scenario {r.scene} " + " ".join(r.flags)


def test_both_scenes_have_a_rung_at_each_decade(ladder):
    for scene in ("crossing", "cut-in"):
        assert sorted({r.decade for r in ladder.RUNGS if r.scene == scene}) == [-7, -6, -5, -4], scene
    assert len({r.name for r in ladder.RUNGS}) == len(ladder.RUNGS)


def test_every_reference_holds_its_estimate_and_sits_in_its_decade(ladder):
    for r in ladder.RUNGS:
        ref = r.reference
        if ref is None:
            assert r.no_reference, f"{r.name}: no reference and no word on what would make one"
            continue
        lo, hi = ref.interval
        assert lo < ref.p < hi, r.name
        assert (lo, hi) == pytest.approx(clopper_pearson(ref.failures, ref.rollouts), rel=1e-12)
        assert abs(math.log10(ref.p) - r.decade) <= 0.5, f"{r.name}: p = {ref.p:.3g} is not near 1e{r.decade}"
        assert ref.command.startswith(("pemviz run", "python benchmarks/")), r.name


def test_a_row_gives_the_runs_median_error_coverage_and_cost(ladder):
    r = ladder.rung("cut-in-1e-4")
    p = r.reference.p
    truth = math.log(p)

    def run(seed, ratio, interval, verdict="reliable", half=0.3):
        log_mu = truth + math.log(ratio)
        return {
            "rung": r.name,
            "seed": seed,
            "log_mu": log_mu,
            "lo": log_mu - half,
            "hi": log_mu + half,
            "interval": interval,
            "verdict": verdict,
            "plain": False,
            "sims": 10_000,
            "cpu_s": 20.0,
            "plain_cpu_s": 1e-3,
        }

    # relative errors 0.1, 0.2, 0.5, 1.5 (median 0.35); the last is outside x2 and reliable, its interval misses p
    runs = [run(0, 1.1, True), run(1, 0.8, True), run(2, 1.5, False, "doubtful"), run(3, 2.5, True, half=0.1)]
    line = ladder.row(r, runs)
    cells = [c.strip() for c in line.strip("|").split("|")]
    assert cells[4] == "0.350"
    assert cells[5] == "3/4"
    assert cells[6] == "2/3 of 4"  # 3 printed intervals, 2 hold p
    assert cells[7] == "1" and cells[8] == "0"
    mc = (0.6745 / 0.35) ** 2 * (1 - p) / p
    assert cells[12] == f"{mc:,.0f}"
    assert cells[13] == f"{10_000 / mc:.2g} / {20_000 / mc:.2g}"
    assert "median <= 0.2" in cells[14] and "no reliable outside x2" in cells[14]


def test_an_existing_out_is_kept_unless_asked(ladder, tmp_path, capsys):
    out = tmp_path / "runs.jsonl"
    out.write_text('{"rung": "cut-in-1e-4", "seed": 0}\n', encoding="utf-8")
    with pytest.raises(SystemExit) as exc:
        ladder.main(["--rungs", "cut-in-1e-4", "--out", str(out)])
    assert exc.value.code == 2
    assert "give --resume or --overwrite" in capsys.readouterr().err
    assert out.read_text(encoding="utf-8") == '{"rung": "cut-in-1e-4", "seed": 0}\n'
    with pytest.raises(SystemExit) as exc:
        ladder.main(["--rungs", "cut-in-1e-9"])
    assert exc.value.code == 2
    assert "the rungs are" in capsys.readouterr().err
