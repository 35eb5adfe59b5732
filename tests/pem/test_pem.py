"""pemviz.pem: encoding, the ML-NN, the braking mapping, the shipped weights and the authors' PEM."""

from __future__ import annotations

import math
import statistics
from pathlib import Path

import numpy as np
import pytest
import torch
from pemviz import pem
from pemviz.cli import main as cli_main
from pemviz.core.files import repo_root
from pemviz.io import data
from pemviz.pem.encoding import BRAKING_CAMERA_TO_LEAD_CENTRE_M, POSE_COLUMNS, NormStats, bce_from_logits
from pemviz.pem.modules import MLNN
from pemviz.pem.network import PemFormatError
from pemviz.pem.recipes import BEST_PEM_NAME
from pemviz.pem.store import ASSETS_DIR_ENV, load_reference_pem, pem_path, reference_pem_dir
from pemviz.pem.training import PemRecipe, train_pem
from pemviz.pem.trees import export_hist_gradient_boosting

from conftest import float64_network

SHARED = repo_root().parent / "shared"
needs_shared_data = pytest.mark.skipif(
    not (SHARED / "data" / "kitti-salient" / data.INPUTS_FILE).is_file(),
    reason=f"KITTI salient files absent from {SHARED / 'data' / 'kitti-salient'}",
)
needs_reference = pytest.mark.skipif(
    not (reference_pem_dir() / "pem_class_train_full.pt").is_file(),
    reason=f"the authors' PEM is absent from {reference_pem_dir()}",
)
GAPS_INSIDE_10_M = np.linspace(2.0, 10.0, 81)
GAPS_2_TO_13_M = np.linspace(2.0, 13.0, 111)


@pytest.fixture(scope="module")
def salient() -> data.SalientData:
    if not (SHARED / "data" / "kitti-salient" / data.INPUTS_FILE).is_file():
        pytest.skip("KITTI salient files absent")
    return data.load_salient_data(SHARED / "data" / "kitti-salient")


@pytest.fixture(scope="module")
def shipped() -> pem.PEM:
    return pem.load_pem()


def _raw_row(cls: int, occ: int, x: float, y: float, z: float, rot: float) -> list[float]:
    return [cls, 0.1, occ, 0.5, 1.6, 1.7, 3.9, x, y, z, rot]


# ---------------------------------------------------------------------------------------- encoding


def test_encoding_is_one_hot_class_and_occlusion_then_z_scored_pose_hand_computed() -> None:
    raw = np.array(
        [
            _raw_row(3, 1, 1.0, 2.0, 30.0, 0.5),
            _raw_row(6, 2, -3.0, 1.0, 10.0, -1.5),
            _raw_row(0, 0, 5.0, 1.5, 50.0, 3.0),
        ]
    )
    norm = pem.fit_norm_stats(raw)
    for j, col in enumerate(POSE_COLUMNS):  # independent truth: statistics.mean / stdev (n - 1)
        assert norm.mean[j] == pytest.approx(statistics.mean(raw[:, col]), rel=1e-12)
        assert norm.std[j] == pytest.approx(statistics.stdev(raw[:, col]), rel=1e-12)
    enc = pem.encode_salient(raw, norm)
    assert enc.shape == (3, 14)
    assert enc[0, :10].tolist() == [0, 0, 0, 1, 0, 0, 0, 0, 1, 0]
    assert enc[1, :10].tolist() == [0, 0, 0, 0, 0, 0, 1, 0, 0, 1]
    assert enc[2, :10].tolist() == [1, 0, 0, 0, 0, 0, 0, 1, 0, 0]
    # z of loc_z = 30 in {30, 10, 50}: mean 30 -> 0; loc_x = 1 in {1, -3, 5}: mean 1 -> 0
    assert enc[0, 12] == pytest.approx(0.0, abs=1e-15) and enc[0, 10] == pytest.approx(0.0, abs=1e-15)
    assert enc[1, 12] == pytest.approx(-20.0 / 20.0)  # stdev of {30, 10, 50} is 20


@pytest.mark.parametrize(
    ("row", "what"),
    [
        (_raw_row(7, 0, 0, 1, 10, 0), "class 7"),
        (_raw_row(0, 3, 0, 1, 10, 0), "occlusion 3"),
        (_raw_row(1.5, 0, 0, 1, 10, 0), "class 1.5"),
    ],
)
def test_encoding_rejects_classes_and_occlusions_outside_the_paper_sets(row, what) -> None:
    norm = NormStats(mean=np.zeros(4), std=np.ones(4))
    with pytest.raises(ValueError, match=f"{what} in row 1"):
        pem.encode_salient(np.array([_raw_row(0, 0, 0, 1, 10, 0), row]), norm)


@needs_shared_data
@needs_reference
def test_norm_stats_of_the_full_file_match_the_authors_stats(salient) -> None:
    norm = pem.fit_norm_stats(salient.inputs)
    ref = load_reference_pem().norm  # float32 torch .std() (unbiased) of the same file
    np.testing.assert_allclose(norm.mean, ref.mean, rtol=1e-5)
    np.testing.assert_allclose(norm.std, ref.std, rtol=1e-5)


def test_braking_salient_inputs_follow_spec_section_2() -> None:
    raw = pem.braking_salient_inputs(np.array([[5.0, 9.88]]))
    assert raw.shape == (2, 11)
    for row, gap in zip(raw, (5.0, 9.88), strict=False):
        assert row[0] == 0 and row[2] == 0  # Car, not occluded
        assert row[7] == 0.0 and row[8] == 1.76
        assert row[9] == pytest.approx(gap + 2.48, abs=1e-12)
        assert row[10] == pytest.approx(-math.pi / 2, abs=1e-15)


# --------------------------------------------------------------------------------------- evaluation


def _random_pem(seed: int, hidden=(20, 20), temperature: float = 1.0) -> pem.PEM:
    torch.manual_seed(seed)
    module = MLNN(hidden=hidden)
    with torch.no_grad():  # non-trivial BatchNorm statistics
        for m in module.modules():
            if isinstance(m, torch.nn.BatchNorm1d):
                m.running_mean.uniform_(-1, 1)
                m.running_var.uniform_(0.2, 3)
                m.weight.uniform_(0.5, 2)
                m.bias.uniform_(-1, 1)
    norm = NormStats(mean=[-1.73, 1.66, 28.16, -0.11], std=[8.28, 0.40, 17.33, 1.71])
    return pem.PEM.from_module(module, norm, name="random", hidden=hidden, temperature=temperature)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_folded_float64_network_equals_torch_eval_mode_forward(seed) -> None:
    p = _random_pem(seed)
    rng = np.random.default_rng(seed)
    raw = np.column_stack(
        [
            rng.integers(0, 7, 500),
            rng.uniform(0, 1, 500),
            rng.integers(0, 3, 500),
            rng.normal(size=(500, 4)),
            rng.normal(0, 8, 500),
            rng.normal(1.6, 0.4, 500),
            rng.uniform(2, 80, 500),
            rng.uniform(-3, 3, 500),
        ]
    )
    module = p.to_module().double()  # torch's own BatchNorm in eval mode, float64
    with torch.no_grad():
        expected = module(torch.as_tensor(p.features(raw))).squeeze(1).numpy()
    np.testing.assert_allclose(float64_network(p._layers, p.features(raw))[:, 0], expected, rtol=0, atol=1e-10)
    # the PEM's own products are order-free on 24-bit grids (GridMLP): float32's precision, measured <= 2e-6 here
    np.testing.assert_allclose(p.logit(raw), expected, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize(
    ("seed", "hidden", "temperature"), [(0, (20, 20), 1.0), (3, (20, 20), 1.7), (4, (32, 16, 8), 0.8)]
)
def test_logit_at_gap_equals_full_evaluation_to_1e9_including_at_the_kinks(seed, hidden, temperature) -> None:
    p = _random_pem(seed, hidden, temperature)
    rng = np.random.default_rng(seed)
    knots = p._gap_knots  # the exact pieces' boundaries: the hardest points
    gaps = np.concatenate([rng.uniform(-50, 300, 20000), knots, knots + 1e-7, knots - 1e-7, [0.0, 2.0, 12.293]])
    features = p.features(pem.braking_salient_inputs(gaps))
    exact = float64_network(p._layers, features)[:, 0] / temperature
    np.testing.assert_allclose(p.logit_at_gap(gaps), exact, rtol=0, atol=1e-9)
    # against the order-free grid form of any row (GridMLP, float32's precision): measured <= 4e-6 here
    np.testing.assert_allclose(p.logit_at_gap(gaps), p.logit(pem.braking_salient_inputs(gaps)), rtol=1e-5, atol=1e-5)
    assert p.logit_at_gap(np.full((2, 3), 7.0)).shape == (2, 3)


def test_bce_from_logits_matches_torch_on_extreme_logits() -> None:
    logits = np.array([-800.0, -30.0, -1.0, 0.0, 2.0, 40.0, 900.0])
    labels = np.array([0.0, 1.0, 1.0, 0.0, 1.0, 0.0, 1.0])
    expected = torch.nn.functional.binary_cross_entropy_with_logits(torch.tensor(logits), torch.tensor(labels)).item()
    assert bce_from_logits(logits, labels) == pytest.approx(expected, rel=1e-12)


# --------------------------------------------------------------------------------------- save / load


def test_save_load_round_trip_is_exact_and_weights_only_loadable(tmp_path: Path) -> None:
    p = _random_pem(5, temperature=1.3)
    out = pem.save_pem(p, tmp_path / "x.pt")
    payload = torch.load(out, weights_only=True)
    assert payload["format"] == "pemviz-pem" and payload["hidden"] == [20, 20]
    q = pem.load_pem(out)
    gaps = np.linspace(0, 60, 301)
    assert np.array_equal(q.logit_at_gap(gaps), p.logit_at_gap(gaps))
    assert q.temperature == 1.3 and np.array_equal(q.norm.std, p.norm.std)
    assert [f.name for f in tmp_path.iterdir()] == ["x.pt"]  # no temp file left


def test_load_pem_errors_name_the_problem(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match="shipped PEMs"):
        pem.load_pem(tmp_path / "missing.pt")
    bad = tmp_path / "bad.pt"
    torch.save({"a": torch.zeros(1)}, bad)
    with pytest.raises(PemFormatError, match="not a pemviz PEM"):
        pem.load_pem(bad)
    junk = tmp_path / "junk.pt"
    junk.write_bytes(b"not a torch file")
    with pytest.raises(PemFormatError, match="not a readable PEM"):
        pem.load_pem(junk)
    allowed = "give a PEM file pemviz wrote (pemviz pem train, save_pem) or a shipped PEM (gbt, ml-nn)"
    for content, kind in (
        (b"101\nsecond line\n", "it is a text file whose first line is '101'"),  # was: (101), torch's message
        (b"", "it is empty"),
        (b"\x80\x02\xff\xfe\x00junk", "it is binary data not written by torch.save"),
        (b"PK\x03\x04broken", "it is a zip archive torch cannot read (damaged, or not written by torch.save)"),
    ):
        junk.write_bytes(content)
        with pytest.raises(PemFormatError) as refused:
            pem.load_pem(junk)
        assert str(refused.value) == f"{junk}: not a readable PEM file ({kind}): {allowed}"


def test_save_to_an_unwritable_folder_raises_and_writes_nothing(tmp_path: Path) -> None:
    with pytest.raises(OSError):
        pem.save_pem(_random_pem(0), tmp_path / "no-such-folder" / "x.pt")
    assert list(tmp_path.iterdir()) == []


# ------------------------------------------------------------------------------------------ training


def test_training_is_seeded_and_learns_a_known_logistic_dependence_on_distance() -> None:
    # Synthetic truth: p(detect) = sigmoid(4 - 0.08 * loc_z), every class/occlusion alike.
    rng = np.random.default_rng(0)
    n = 20000
    z = rng.uniform(2, 80, n)
    raw = np.column_stack(
        [
            rng.integers(0, 7, n),
            np.zeros(n),
            rng.integers(0, 3, n),
            np.zeros((n, 4)),
            rng.normal(0, 5, n),
            rng.normal(1.7, 0.3, n),
            z,
            rng.uniform(-3, 3, n),
        ]
    )
    p_true = 1 / (1 + np.exp(-(4 - 0.08 * z)))
    y = (rng.uniform(size=n) < p_true).astype(float)
    a, b, c = (train_pem(PemRecipe("t", "", epochs=20, batch_size=512, lr=3e-3, seed=s), raw, y) for s in (7, 7, 8))
    assert np.array_equal(a.logit(raw), b.logit(raw))
    assert not np.array_equal(a.logit(raw), c.logit(raw))
    # Within 0.05 of the truth at the bulk of the data, and its BCE close to the true model's.
    probe = pem.braking_salient_inputs(np.array([10.0, 30.0, 50.0]))
    truth = 1 / (1 + np.exp(-(4 - 0.08 * probe[:, 9])))
    np.testing.assert_allclose(a.prob(probe), truth, atol=0.03)
    true_bce = bce_from_logits(np.log(p_true / (1 - p_true)), y)
    assert bce_from_logits(a.logit(raw), y) < true_bce + 0.01


def test_train_rejects_labels_outside_0_1() -> None:
    raw = pem.braking_salient_inputs(np.arange(4.0))
    with pytest.raises(ValueError, match="0 or 1"):
        train_pem(PemRecipe("t", "", epochs=1), raw, np.array([0, 1, 2, 1]))


# ------------------------------------------------------------------------------ shipped weights (issue 3)


def test_shipped_pem_gives_p_detect_in_0_98_0_999_inside_10_m(shipped) -> None:
    p = shipped.prob_at_gap(GAPS_INSIDE_10_M)
    assert p.min() >= 0.98 and p.max() <= 0.999, (p.min(), p.max())
    assert shipped.name == "ml-nn" and shipped.hidden == (20, 20) and shipped.batch_norm


def test_shipped_file_is_small_and_records_its_training_command() -> None:
    path = pem_path("ml-nn")
    assert path.stat().st_size < 20_000
    meta = pem.load_pem(path).metadata
    assert meta["command"].startswith("pemviz pem train --model ml-nn")
    assert meta["data_sha256"] == data.FILE_SHA256[data.INPUTS_FILE]


@needs_shared_data
def test_shipped_pem_full_data_bce_beats_guess_mu(shipped, salient) -> None:
    guess_mu = bce_from_logits(
        np.full(len(salient), math.log(salient.labels.mean() / (1 - salient.labels.mean()))), salient.labels
    )
    assert guess_mu == pytest.approx(0.2595, abs=5e-4)  # the paper's Guess-mu BCE
    bce = bce_from_logits(shipped.logit(salient.inputs), salient.labels)
    assert bce < 0.2595 - 0.03, bce


@needs_reference
def test_authors_pem_reproduces_the_spec_numbers() -> None:
    ref = load_reference_pem()
    assert ref.prob_at_gap(12.293) == pytest.approx(0.985, abs=0.002)
    p = ref.prob_at_gap(GAPS_INSIDE_10_M)
    assert 0.9905 <= p.min() and p.max() <= 0.9955


@needs_reference
def test_shipped_pem_agrees_with_the_authors_pem_within_0_01_for_gaps_2_to_13_m(shipped) -> None:
    ref = load_reference_pem()
    diff = np.abs(shipped.prob_at_gap(GAPS_2_TO_13_M) - ref.prob_at_gap(GAPS_2_TO_13_M))
    assert diff.max() <= 0.01, diff.max()


def test_assets_dir_env_override(tmp_path: Path, monkeypatch) -> None:
    pem.save_pem(_random_pem(1), tmp_path / "pem_mine.pt")
    monkeypatch.setenv(ASSETS_DIR_ENV, str(tmp_path))
    assert pem.load_pem("mine").name == "random"
    with pytest.raises(FileNotFoundError, match="mine"):
        pem.load_pem("other")


# ---------------------------------------------------------------------------------------------- CLI


@needs_shared_data
def test_cli_pem_train_writes_a_loadable_pem(tmp_path: Path, capsys) -> None:
    out = tmp_path / "p.pt"
    assert cli_main(["pem", "train", "--epochs", "1", "--out", str(out), "--no-progress"]) == 0
    printed = capsys.readouterr().out
    assert "BCE on the full training file" in printed and str(out) in printed
    assert pem.load_pem(out).metadata["epochs"] == 1


@pytest.mark.parametrize(
    ("argv", "message"),
    [(["--epochs", "0"], "--epochs"), (["--model", "nope"], "--model"), (["--out", "x.txt"], ".pt")],
)
def test_cli_pem_train_bad_values_exit_2_and_write_nothing(tmp_path: Path, capsys, argv, message) -> None:
    argv = [a if a != "x.txt" else str(tmp_path / "x.txt") for a in argv]
    assert (
        cli_main(
            ["pem", "train", "--out", str(tmp_path / "p.pt"), *argv] if "--out" not in argv else ["pem", "train", *argv]
        )
        == 2
    )
    assert message in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []


# ------------------------------------------------------------------------------ boosted trees (issue 4)


@pytest.fixture(scope="module")
def small_hgb():
    """A scikit-learn HistGradientBoostingClassifier on synthetic encoded features (the oracle)."""
    from sklearn.ensemble import HistGradientBoostingClassifier

    rng = np.random.default_rng(3)
    n = 4000
    raw = np.column_stack(
        [
            rng.integers(0, 7, n),
            np.zeros(n),
            rng.integers(0, 3, n),
            np.zeros((n, 4)),
            rng.normal(0, 5, n),
            rng.normal(1.7, 0.3, n),
            rng.uniform(2, 80, n),
            rng.uniform(-3, 3, n),
        ]
    )
    y = (rng.uniform(size=n) < 1 / (1 + np.exp(-(4 - 0.06 * raw[:, 9] - 0.5 * raw[:, 2])))).astype(int)
    norm = pem.fit_norm_stats(raw)
    model = HistGradientBoostingClassifier(max_iter=40, max_leaf_nodes=15, early_stopping=False, random_state=0)
    model.fit(pem.encode_salient(raw, norm), y)
    return model, norm, raw


def test_exported_trees_equal_scikit_learn_decision_function(small_hgb) -> None:
    model, norm, raw = small_hgb
    tree = export_hist_gradient_boosting(model, norm, name="t")
    assert tree.roots.shape[0] == 40
    np.testing.assert_allclose(
        tree.logit(raw), model.decision_function(pem.encode_salient(raw, norm)), rtol=0, atol=1e-10
    )


def test_tree_logit_at_gap_is_exactly_the_full_evaluation_also_at_the_thresholds(small_hgb) -> None:
    model, norm, _ = small_hgb
    tree = export_hist_gradient_boosting(model, norm, name="t")
    thr_gap = tree._gap_z_thresholds * norm.std[2] + norm.mean[2] - BRAKING_CAMERA_TO_LEAD_CENTRE_M
    assert thr_gap.size > 10
    gaps = np.concatenate(
        [
            np.linspace(-10, 120, 5001),
            thr_gap,
            np.nextafter(thr_gap, np.inf),
            thr_gap + 1e-9,
            np.nextafter(thr_gap, -np.inf),
        ]
    )
    np.testing.assert_array_equal(tree.logit_at_gap(gaps), tree.logit(pem.braking_salient_inputs(gaps)))


def test_tree_pem_round_trips_through_a_compact_weights_only_file(small_hgb, tmp_path: Path) -> None:
    model, norm, raw = small_hgb
    tree = export_hist_gradient_boosting(model, norm, name="t", metadata={"a": 1})
    path = pem.save_pem(tree, tmp_path / "t.pt")
    assert torch.load(path, weights_only=True)["kind"] == "gbt"
    back = pem.load_pem(path)
    assert isinstance(back, pem.TreePEM) and back.metadata == {"a": 1}
    np.testing.assert_array_equal(back.logit(raw), tree.logit(raw))
    internal = int((~tree.is_leaf).sum())
    assert path.stat().st_size < 4000 + 17 * internal + 9 * tree.is_leaf.size  # int8/int32 splits, leaf values


def test_shipped_gbt_pem_curve_and_full_data_fit(salient) -> None:
    gbt = pem.load_pem(BEST_PEM_NAME)
    assert isinstance(gbt, pem.TreePEM) and gbt.roots.shape[0] == 300
    p = gbt.prob_at_gap(GAPS_INSIDE_10_M)
    assert p.min() >= 0.98 and p.max() <= 0.999, (p.min(), p.max())
    assert gbt.metadata["command"].startswith("pemviz pem train --model gbt")
    rows = slice(None, None, 5)  # every 5th row keeps the test fast
    bce = bce_from_logits(gbt.logit(salient.inputs[rows]), salient.labels[rows])
    assert bce < bce_from_logits(pem.load_pem("ml-nn").logit(salient.inputs[rows]), salient.labels[rows]) - 0.03


# ------------------------------------------------------------------------------------- B-NN (issue 4)


def test_bnn_predictive_mean_is_the_mean_of_the_sample_probabilities() -> None:
    from pemviz.pem.bayes import BayesianPEM

    rng = np.random.default_rng(0)
    s, h = 7, 5
    weights = {
        "w1": rng.normal(size=(s, 14, h)),
        "b1": rng.normal(size=(s, h)),
        "w2": rng.normal(size=(s, h, h)),
        "b2": rng.normal(size=(s, h)),
        "w3": rng.normal(size=(s, h, 1)),
        "b3": rng.normal(size=(s, 1)),
    }
    bnn = BayesianPEM(name="b", norm=NormStats(mean=np.zeros(4), std=np.ones(4)), weights=weights)
    x = rng.normal(size=(300, 14))
    probs = []
    for k in range(s):  # independent: torch, sample by sample
        w = {n: torch.as_tensor(v[k]) for n, v in weights.items()}
        hid = torch.relu(torch.relu(torch.as_tensor(x) @ w["w1"] + w["b1"]) @ w["w2"] + w["b2"])
        probs.append(torch.sigmoid(hid @ w["w3"] + w["b3"]).squeeze(1).numpy())
    mean_p = np.mean(probs, axis=0)
    np.testing.assert_allclose(
        bnn.logit_features(x, chunk=64), np.log(mean_p) - np.log1p(-mean_p), rtol=1e-9, atol=1e-9
    )


def test_bnn_training_runs_seeded_and_checks_its_site_order() -> None:
    from pemviz.pem.bayes import train_bnn_pem

    raw = pem.braking_salient_inputs(np.linspace(2, 60, 400))
    y = (raw[:, 9] < 40).astype(float)
    norm = NormStats(mean=[0.0, 1.7, 30.0, 0.0], std=[1.0, 0.4, 17.0, 1.7])
    a = train_bnn_pem(raw, y, steps=30, batch_size=128, n_samples=16, seed=4, norm=norm)
    b = train_bnn_pem(raw, y, steps=30, batch_size=128, n_samples=16, seed=4, norm=norm)
    assert a.n_samples == 16 and a.weights["w2"].shape == (16, 20, 20)
    np.testing.assert_array_equal(a.logit(raw), b.logit(raw))
