"""pemviz.studies.pem_eval: metrics against hand-computed values and scikit-learn, the reduced cross-validation
(one fold, few epochs) in sane ranges, the table files and the rerun recording read back."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from pemviz import pem
from pemviz.cli import main as cli_main
from pemviz.core.files import repo_root
from pemviz.io import data
from pemviz.pem.store import load_reference_pem
from pemviz.studies.pem_eval import (
    GAP_GRID_M,
    EvalConfig,
    evaluate_pems,
    expected_calibration_error,
    format_csv,
    format_markdown,
    reliability_curve,
    score,
    stratified_folds,
)
from pemviz.studies.pem_eval_recording import write_recording

from conftest import verify_rrd

SHARED_DATA = repo_root().parent / "shared" / "data" / "kitti-salient"
QUICK = EvalConfig(folds=(0,), mlnn_epochs=20, gbt_trees=60, bnn_steps=200, bnn_samples=100)


@pytest.fixture(scope="module")
def salient() -> data.SalientData:
    if not (SHARED_DATA / data.INPUTS_FILE).is_file():
        pytest.skip(f"KITTI salient files absent from {SHARED_DATA}")
    return data.load_salient_data(SHARED_DATA)


@pytest.fixture(scope="module")
def quick(salient):
    return evaluate_pems(salient.inputs, salient.labels, QUICK, data_source="test")


# ------------------------------------------------------------------------------------------- metrics


def test_ece_hand_computed() -> None:
    # 10 bins: [0.05] -> bin 0, |0.05 - 0| ; [0.15] -> bin 1, |0.15 - 1| ; [0.95, 0.95] -> bin 9, |0.95 - 0.5|
    p = np.array([0.05, 0.15, 0.95, 0.95])
    y = np.array([0.0, 1.0, 1.0, 0.0])
    assert expected_calibration_error(p, y, n_bins=10) == pytest.approx(0.25 * 0.05 + 0.25 * 0.85 + 0.5 * 0.45)


def test_reliability_bins_are_equal_width_with_p_1_in_the_last_and_empty_bins_nan() -> None:
    mean_p, rate, count = reliability_curve(np.array([0.0, 1.0 / 15, 0.999, 1.0]), np.array([0, 1, 1, 1]), 15)
    assert count.tolist() == [1, 1] + [0] * 12 + [2]
    assert mean_p[14] == pytest.approx(0.9995) and rate[14] == 1.0
    assert np.isnan(mean_p[5]) and np.isnan(rate[5])


def test_a_perfectly_calibrated_sample_has_small_ece() -> None:
    rng = np.random.default_rng(0)
    p = rng.uniform(0.6, 1.0, 200_000)
    y = (rng.uniform(size=p.size) < p).astype(float)
    assert expected_calibration_error(p, y) < 0.003
    assert expected_calibration_error(np.clip(p + 0.05, 0, 1), y) > 0.04  # a biased one does not


def test_score_matches_scikit_learn() -> None:
    from sklearn.metrics import average_precision_score, log_loss, roc_auc_score

    rng = np.random.default_rng(1)
    logit = rng.normal(2.5, 1.5, 3000)
    y = (rng.uniform(size=3000) < 1 / (1 + np.exp(-logit))).astype(float)
    p = 1 / (1 + np.exp(-logit))
    bce, auc, ap, _ = score(logit, y)
    assert bce == pytest.approx(log_loss(y, p), rel=1e-9)
    assert auc == pytest.approx(roc_auc_score(y, p), abs=1e-12)
    assert ap == pytest.approx(average_precision_score(y, p), abs=1e-12)


def test_folds_are_stratified_in_file_order_and_partition_the_rows() -> None:
    y = np.array([1] * 90 + [0] * 10)
    folds = stratified_folds(y, 5)
    tests = [te for _, te in folds]
    assert np.array_equal(np.sort(np.concatenate(tests)), np.arange(100))
    for tr, te in folds:
        assert y[te].sum() == 18 and (y[te] == 0).sum() == 2  # stratified
        assert np.all(np.diff(te) > 0) and np.intersect1d(tr, te).size == 0
    assert tests[0][:18].tolist() == list(range(18))  # no shuffle: the first positives form fold 0


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"models": ("nope",)}, "nope"),
        ({"folds": (5,)}, "folds"),
        ({"n_splits": 1}, "n_splits"),
        ({"mlnn_epochs": 0}, "mlnn_epochs"),
    ],
)
def test_eval_config_rejects_bad_values(kwargs, message) -> None:
    with pytest.raises(ValueError, match=message):
        EvalConfig(**kwargs)


# ------------------------------------------------------------------------------- reduced CV (CI size)


def test_reduced_cv_numbers_are_in_sane_ranges(quick) -> None:
    by = {m.name: m for m in quick.models}
    assert by["guess-mu"].mean("bce") == pytest.approx(0.2595, abs=0.001)  # paper Table I
    assert by["guess-mu"].mean("auc") == 0.5
    assert by["lr"].mean("bce") == pytest.approx(0.244, abs=0.004)  # paper 0.244 / 0.688 (full protocol)
    assert by["lr"].mean("auc") == pytest.approx(0.688, abs=0.01)
    assert 0.215 < by["ml-nn"].mean("bce") < 0.245 and 0.70 < by["ml-nn"].mean("auc") < 0.80  # 20 epochs
    assert 0.22 < by["b-nn"].mean("bce") < 0.26 and 0.6 < by["b-nn"].mean("auc") < 0.8  # 200 SVI steps
    assert by["gbt"].mean("bce") < 0.22 and by["gbt"].mean("auc") > 0.79  # 60 trees already beat the paper
    for m in quick.models:
        assert 0.0 <= m.mean("ece") < 0.03, m.name
        assert 0.92 < m.mean("ap") <= 1.0
        assert m.test_rows.shape == (7500,) and m.gap_prob.shape == (1, GAP_GRID_M.size)
    assert quick.best() == "gbt"


def test_out_of_fold_logits_are_the_fold_models_own(quick, salient) -> None:
    # The LR's logits equal scikit-learn's own decision function refitted on the same training fold.
    from sklearn.linear_model import LogisticRegression

    tr, te = stratified_folds(salient.labels)[0]
    norm = pem.fit_norm_stats(salient.inputs)
    lr = LogisticRegression(max_iter=10000).fit(pem.encode_salient(salient.inputs[tr], norm), salient.labels[tr])
    expected = lr.decision_function(pem.encode_salient(salient.inputs[te], norm))
    lr_eval = quick.model("lr")
    assert np.array_equal(lr_eval.test_rows, te)
    np.testing.assert_allclose(lr_eval.logits, expected, rtol=0, atol=1e-9)


def test_tables_have_one_row_per_model_and_fold(quick) -> None:
    md = format_markdown(quick)
    for name in ("ml-nn", "lr", "guess-mu", "b-nn", "gbt"):
        assert f"| {name} |" in md or f"| **{name}** |" in md
    lines = format_csv(quick).strip().splitlines()
    assert lines[0] == "model,fold,n_test,bce,roc_auc,average_precision,ece,fit_s"
    assert len(lines) == 1 + 5 * 2  # one fold + the mean row per model
    gm = [ln for ln in lines if ln.startswith("guess-mu,0,")][0].split(",")
    assert float(gm[3]) == pytest.approx(quick.model("guess-mu").folds[0].bce, abs=1e-6)


def test_recording_passes_rrd_verify_and_reads_back(quick, tmp_path: Path) -> None:
    rr = pytest.importorskip("rerun")
    path = write_recording(quick, tmp_path / "eval.rrd")
    assert [p.name for p in tmp_path.iterdir()] == ["eval.rrd"]
    verify_rrd(path)
    pytest.importorskip("datafusion", reason="rerun-sdk[catalog] reads recordings back")
    with rr.server.Server(datasets={"eval": [str(path)]}) as server:
        client = server.client()
        table = client.get_dataset("eval").reader(index=None).to_arrow_table()
    cols = table.column_names

    def strip(entity: str) -> np.ndarray:
        name = f"/{entity}:LineStrips2D:strips"
        assert name in cols, name
        values = [v for v in table.column(name).to_pylist() if v is not None]
        return np.asarray(values[0][0])

    for m in ("ml-nn", "lr", "guess-mu", "b-nn", "gbt"):
        roc = strip(f"roc/data/{m}")
        np.testing.assert_allclose(roc[0], [0, 0]) and np.testing.assert_allclose(roc[-1], [1, 1])
        assert strip(f"gap/data/{m}").shape == (GAP_GRID_M.size, 2)
    if quick.authors_gap_prob is not None:
        authors = strip("gap/data/authors")
        np.testing.assert_allclose(authors[:, 1], load_reference_pem().prob_at_gap(GAP_GRID_M), atol=1e-6)


# ----------------------------------------------------------------------------------------------- CLI


def test_cli_eval_writes_tables_and_recording(salient, tmp_path: Path, capsys) -> None:
    rc = cli_main(["pem", "eval", "--quick", "--models", "lr,guess-mu", "--out", str(tmp_path)])
    assert rc == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["pem-eval.csv", "pem-eval.md", "pem-eval.rrd"]
    assert "lr" in capsys.readouterr().out


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--models", "lr,xgboost"], "xgboost"),
        (["--folds", "0,9"], "folds"),
        (["--folds", "a"], "--folds"),
        (["--save", "x.txt"], ".rrd"),
        (["--ensemble", "1"], "--ensemble 1"),
    ],
)
def test_cli_eval_bad_values_exit_2_and_write_nothing(tmp_path: Path, capsys, argv, message) -> None:
    argv = [str(tmp_path / a) if a == "x.txt" else a for a in argv]
    assert cli_main(["pem", "eval", "--quick", "--out", str(tmp_path), *argv]) == 2
    assert message in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []


def test_cli_eval_cross_validates_the_ensemble_members_beside_the_nominal(salient, tmp_path: Path, capsys) -> None:
    from pemviz.pem.ensemble import bootstrap_rows
    from pemviz.pem.recipes import PEM_RECIPES
    from pemviz.studies.ensemble_eval import _member_fold
    from pemviz.studies.pem_eval import stratified_folds

    rc = cli_main(
        ["pem", "eval", "--quick", "--models", "ml-nn", "--ensemble", "2", "--no-record", "--out", str(tmp_path)]
    )
    assert rc == 0
    text = (tmp_path / "pem-eval-ensemble.md").read_text()
    assert "| ml-nn (nominal) |" in text and "| member 0 |" in text and "| member 1 |" in text
    # member 1's fold-0 row: the same fit by hand (bootstrap rows of the training fold, the recipe's seed + 2)
    raw, y = salient.inputs.astype(float), salient.labels.astype(float)
    train, test = stratified_folds(y)[0]
    from pemviz.pem.encoding import fit_norm_stats

    k, fold, bce, auc = _member_fold(
        (1, 0, raw[train], y[train], raw[test], y[test], fit_norm_stats(raw), PEM_RECIPES["ml-nn"].seed, 20, 15)
    )
    assert f"| member 1 | {bce:.4f} | {auc:.4f} |" in text
    assert 0.2 < bce < 0.3 and 0.6 < auc < 0.9
    assert len(set(bootstrap_rows(len(train), 2, 1))) < len(train)
