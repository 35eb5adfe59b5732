"""The noise PEM: camera geometry on hand-computed cases, densities against torch.distributions and closed forms, a
fit on synthetic heteroscedastic data with a known scale function, the real KITTI files (held-out NLL and coverage),
files, the label reader, and the command line."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from pemviz import pem
from pemviz.cli import main as cli_main
from pemviz.core.files import repo_root
from pemviz.io import data
from pemviz.pem.camera import KITTI_FOCAL_PX, box_errors_to_metric
from pemviz.pem.encoding import NormStats
from pemviz.pem.modules import MLNN, NoiseNLL
from pemviz.pem.network import PemFormatError
from pemviz.pem.noise import (
    HomoscedasticNoise,
    NoisePEM,
    NoiseRecipe,
    fit_homoscedastic,
    nll,
    noise_training_data,
    train_noise_pem,
)
from pemviz.pem.recipes import NOISE_RECIPES
from pemviz.pem.store import noise_pem_path, save_noise_pem
from pemviz.studies import noise_eval
from scipy import special, stats

SHARED_DATA = repo_root().parent / "shared" / "data" / "kitti-salient"
F = KITTI_FOCAL_PX


@pytest.fixture(scope="module")
def salient() -> data.SalientData:
    if not (SHARED_DATA / data.INPUTS_FILE).is_file():
        pytest.skip(f"KITTI salient files absent from {SHARED_DATA}")
    return data.load_salient_data(SHARED_DATA)


def _raw(z: np.ndarray, *, x: float = 0.0, cls: int = 0, occ: int = 0, rot: float = -1.57) -> np.ndarray:
    """Raw salient inputs [R, 11] of obstacles at ranges z (metres)."""
    z = np.asarray(z, dtype=np.float64)
    raw = np.zeros((z.size, 11))
    raw[:, 0], raw[:, 2], raw[:, 7], raw[:, 8], raw[:, 9], raw[:, 10] = cls, occ, x, 1.65, z, rot
    return raw


NORM = NormStats(mean=np.array([0.0, 1.65, 25.0, 0.0]), std=np.array([8.0, 0.5, 15.0, 1.8]))


# ------------------------------------------------------------------------------------------- geometry


def test_kitti_focal_length_is_p2_of_the_calibration_files() -> None:
    assert KITTI_FOCAL_PX == 721.5377  # P2[0, 0] of KITTI calib/000000.txt


def test_range_error_hand_computed_from_the_pinhole_model() -> None:
    # truth box 55 px high at 20 m; the detector's box is 50 px (e_h = -5): H = 20 * 55 / f, and the detected box
    # reads Z = f H / 50 = 20 * 55 / 50 = 22 m, 2 m too far
    err = box_errors_to_metric([20.0], [50.0], [0.0], [-5.0])
    assert err[0, 0] == pytest.approx(2.0, rel=1e-14) and err[0, 1] == 0.0
    # 60 px box at 12 m, detected 4 px too tall (64 px): Z = 12 * 60 / 64 = 11.25 m
    assert box_errors_to_metric([12.0], [64.0], [0.0], [4.0])[0, 0] == pytest.approx(-0.75, rel=1e-14)


def test_lateral_error_hand_computed_is_the_centre_error_back_projected_at_the_range() -> None:
    # f / 100 pixels at 10 m is 0.1 m; 3 px at 48.10251 m is 3 * 48.10251 / 721.5377 = 0.2 m
    err = box_errors_to_metric([10.0, 48.10251], [40.0, 40.0], [F / 100, 3.0], [0.0, 0.0])
    np.testing.assert_allclose(err[:, 1], [0.1, 0.2], rtol=1e-6)
    np.testing.assert_array_equal(err[:, 0], [0.0, 0.0])


def test_small_height_error_gives_the_z_squared_law() -> None:
    # a car 1.5 m high at 30 m spans f * 1.5 / 30 px; 0.01 px too tall -> dZ ~ -Z^2 e_h / (f H)
    h_t = F * 1.5 / 30.0
    err = box_errors_to_metric([30.0], [h_t + 0.01], [0.0], [0.01])
    assert err[0, 0] == pytest.approx(-(30.0**2) * 0.01 / (F * 1.5), rel=1e-3)


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (([0.5], [40.0], [0.0], [0.0]), ">= 1.0 m"),
        (([10.0], [40.0], [0.0], [40.0]), "must be > 0 pixels"),
        (([10.0, 20.0], [40.0], [0.0], [0.0]), "one length"),
    ],
)
def test_geometry_rejects_bad_input(args, message) -> None:
    with pytest.raises(ValueError, match=message):
        box_errors_to_metric(*args)


def test_training_data_keeps_detected_obstacles_ahead_and_dequantises_within_half_a_pixel() -> None:
    raw = _raw(np.array([20.0, 20.0, 0.5, 40.0]))
    table = np.array(
        [
            [1, 600, 180, 40, 50, 0, 0, 0, -5],  # detected, truth 55 px high
            [0, 0, 0, 0, 0, 0, 0, 0, 0],  # missed
            [1, 600, 180, 40, 50, 1, 0, 0, 1],  # detected but 0.5 m ahead: dropped
            [1, 600, 180, 40, 30, 3, 0, 0, 0],  # detected, centre 3 px off
        ],
        dtype=np.float64,
    )
    d = noise_training_data(raw, table, seed=3)
    assert d.rows.tolist() == [0, 3]
    # row 0: e_h in [-5.5, -4.5] with the truth 55 px: dZ = -20 e_h / (55 + e_h) in [20*4.5/50.5, 20*5.5/49.5]
    assert 20 * 4.5 / 50.5 <= d.errors[0, 0] <= 20 * 5.5 / 49.5
    assert abs(d.errors[0, 1]) <= 0.5 * 20 / F
    assert (2.5 * 40 / F) <= d.errors[1, 1] <= (3.5 * 40 / F)
    np.testing.assert_array_equal(d.errors, noise_training_data(raw, table, seed=3).errors)
    assert not np.array_equal(d.errors, noise_training_data(raw, table, seed=4).errors)


# ---------------------------------------------------------------------------------- densities


def _homo(family: str, df=None) -> HomoscedasticNoise:
    rng = np.random.default_rng(1)
    return HomoscedasticNoise(
        name="h",
        norm=NORM,
        family=family,
        df=df,
        coef=rng.normal(0, 0.3, (14, 2)),
        intercept=np.array([0.2, -0.05]),
        log_scale=np.array([0.4, -2.0]),
    )


def _torch_dist(family: str, loc, scale, df):
    loc, scale = torch.as_tensor(loc), torch.as_tensor(scale)
    if family == "normal":
        return torch.distributions.Normal(loc, scale)
    if family == "laplace":
        return torch.distributions.Laplace(loc, scale)
    return torch.distributions.StudentT(torch.as_tensor(np.asarray(df, dtype=np.float64)), loc, scale)


@pytest.mark.parametrize(("family", "df"), [("normal", None), ("laplace", None), ("student-t", [3.2, 2.6])])
def test_log_prob_matches_torch_distributions_to_1e_12(family, df) -> None:
    model = _homo(family, df)
    rng = np.random.default_rng(0)
    x = model.features(_raw(rng.uniform(2, 70, 500), x=3.0))
    errors = rng.standard_t(3, (500, 2)) * [2.0, 0.1]
    loc, log_scale = model.noise_params(x)
    expected = _torch_dist(family, loc, np.exp(log_scale), df).log_prob(torch.as_tensor(errors)).numpy()
    np.testing.assert_allclose(model.log_prob_dims(x, errors), expected, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(model.log_prob(x, errors), expected.sum(axis=1), rtol=1e-12, atol=1e-12)
    assert model.log_prob(x, errors).dtype == np.float64


def test_student_t_cdf_matches_the_incomplete_beta_closed_form() -> None:
    # F(t) = 1 - I_{nu / (nu + t^2)}(nu / 2, 1 / 2) / 2 for t >= 0 (Abramowitz & Stegun 26.7.1)
    model = _homo("student-t", [3.2, 2.6])
    rng = np.random.default_rng(2)
    x = model.features(_raw(rng.uniform(2, 70, 200)))
    errors = rng.normal(0, 3, (200, 2))
    loc, log_scale = model.noise_params(x)
    t = (errors - loc) / np.exp(log_scale)
    nu = model.df
    tail = 0.5 * special.betainc(nu / 2, 0.5, nu / (nu + t**2))
    np.testing.assert_allclose(model.cdf(x, errors), np.where(t >= 0, 1 - tail, tail), rtol=1e-10, atol=1e-12)


def test_network_parameters_equal_the_torch_module_in_float64() -> None:
    torch.manual_seed(0)
    module = MLNN(14, (8, 8), batch_norm=False, out_dim=4)
    scale = np.array([2.5, 0.08])
    model = NoisePEM(
        name="n",
        norm=NORM,
        family="student-t",
        df=np.array([3.0, 4.0]),
        state_dict=module.state_dict(),
        hidden=(8, 8),
        target_scale=scale,
    )
    x = model.features(_raw(np.linspace(2, 80, 50), x=-4.0, cls=3, occ=1))
    with torch.no_grad():
        out = module.double()(torch.as_tensor(x)).numpy()
    loc, log_scale = model.noise_params(x)
    # order-free products on 24-bit grids (GridMLP): float32's precision of the float64 module's outputs
    np.testing.assert_allclose(loc, out[:, :2] * scale, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(log_scale, out[:, 2:] + np.log(scale), rtol=1e-5, atol=1e-6)


def test_samples_follow_the_model_kolmogorov_smirnov() -> None:
    model = _homo("student-t", [3.2, 2.6])
    x = model.features(_raw(np.repeat([5.0, 50.0], 20000)))
    e = model.sample(x, np.random.default_rng(7))
    loc, log_scale = model.noise_params(x)
    u = (e - loc) / np.exp(log_scale)
    for d in range(2):
        assert stats.kstest(u[:, d], stats.t(model.df[d]).cdf).pvalue > 1e-3
    np.testing.assert_array_equal(e, model.sample(x, np.random.default_rng(7)))
    lo, hi = model.interval(x, 0.9)
    assert np.mean((e >= lo) & (e <= hi)) == pytest.approx(0.9, abs=0.01)  # 40,000 x 2 draws: sd 0.001


def test_noise_loss_is_the_torch_distribution_nll() -> None:
    out = torch.tensor([[0.1, -0.2, 0.3, -1.0], [0.0, 0.5, -0.4, 0.2]])
    y = torch.tensor([[1.0, 0.0], [-2.0, 0.3]])
    loss = NoiseNLL("student-t")
    expected = (
        -torch.distributions.StudentT(1.0 + math.log(2.0), out[:, :2], out[:, 2:].exp()).log_prob(y).sum(1).mean()
    )
    assert float(loss(out, y).detach()) == pytest.approx(float(expected), rel=1e-6)  # softplus(0) = log 2


# --------------------------------------------------------------------------------- synthetic fit


def _synthetic(n: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Obstacles at z ~ U(3, 70) m with Student-t (nu = 4) errors of scale a + b z: range 0.05 + 0.04 z,
    lateral 0.005 + 0.002 z; means 0. Returns raw inputs, errors and the true scales [n, 2]."""
    rng = np.random.default_rng(seed)
    z = rng.uniform(3.0, 70.0, n)
    raw = _raw(z, x=0.0)
    raw[:, 7] = rng.uniform(-10, 10, n)
    raw[:, 10] = rng.uniform(-3, 3, n)
    scale = np.stack([0.05 + 0.04 * z, 0.005 + 0.002 * z], axis=1)
    return raw, rng.standard_t(4.0, (n, 2)) * scale, scale


@pytest.fixture(scope="module")
def synthetic_fit():
    raw, errors, _ = _synthetic(12000, 0)
    model = NOISE_RECIPES["hetero-t"].train(raw, errors, norm=NORM, seed=0)  # the shipped recipe, 100 epochs
    return model, raw, errors


def test_fit_on_synthetic_data_recovers_the_scale_function_and_df(synthetic_fit) -> None:
    model, _, _ = synthetic_fit
    z = np.array([5.0, 15.0, 30.0, 50.0, 65.0])
    _, log_scale = model.noise_params(model.features(_raw(z)))
    truth = np.stack([0.05 + 0.04 * z, 0.005 + 0.002 * z], axis=1)
    np.testing.assert_allclose(np.exp(log_scale), truth, rtol=0.15)
    np.testing.assert_allclose(model.df, [4.0, 4.0], rtol=0.15)  # 3.74, 3.78


def test_fit_on_synthetic_data_beats_the_baseline_and_nears_the_true_model(synthetic_fit) -> None:
    model, raw, errors = synthetic_fit
    test_raw, test_err, scale = _synthetic(6000, 1)
    baseline = fit_homoscedastic(raw, errors, family="normal", norm=NORM)
    oracle = -np.mean(np.sum(stats.t(4.0, 0.0, scale).logpdf(test_err), axis=1))  # the true density
    hetero = nll(model, test_raw, test_err)
    assert hetero < nll(baseline, test_raw, test_err) - 0.5  # 0.874 against 1.587 nats
    assert oracle - 0.01 <= hetero < oracle + 0.02  # the true density: 0.870 nats


def test_training_is_reproducible_with_a_seed() -> None:
    raw, errors, _ = _synthetic(2000, 5)
    a, b, c = (train_noise_pem(NoiseRecipe("t", "", epochs=2, seed=s), raw, errors, norm=NORM) for s in (3, 3, 4))
    for key, value in a.state_dict.items():
        np.testing.assert_array_equal(value, b.state_dict[key], strict=True)
    assert not all(np.array_equal(v, c.state_dict[k]) for k, v in a.state_dict.items())
    np.testing.assert_array_equal(a.df, b.df)


# -------------------------------------------------------------------------------------- KITTI files


@pytest.fixture(scope="module")
def kitti_cv(salient):
    config = noise_eval.NoiseEvalConfig(models=("homo-normal", "homo-t", "hetero-t"), folds=(0,))
    return noise_eval.evaluate_noise_pems(salient.inputs, salient.label_table, config, data_source="test")


def test_kitti_heteroscedastic_beats_the_baselines_in_held_out_nll(kitti_cv) -> None:
    homo, homo_t, hetero = (kitti_cv.model(m).mean("nll") for m in ("homo-normal", "homo-t", "hetero-t"))
    assert hetero < homo_t - 0.4 and homo_t < homo  # fold 0 (5-fold CV): 0.82-0.86 < 1.42 < 2.48 nats
    assert kitti_cv.best() == "hetero-t"
    assert kitti_cv.n_rows == 34745  # 34,787 detected, 42 less than 1 m ahead


CALIBRATION_POINTS = 0.02
"""How far the hetero-t model's central intervals may miss their level beyond the held-out sample's own noise: its
5-fold coverage is 0.794 / 0.899 / 0.949 (80 / 90 / 95 %, range; the assets' README), and one fold's fit, whose last
bits depend on the CPU, moves it by up to 2 points (fold 0: 0.778 at 80 % on an AVX-512 Xeon)."""


def test_kitti_heteroscedastic_coverage_is_calibrated(kitti_cv) -> None:
    cov = kitti_cv.model("hetero-t").mean("coverage")  # [levels 50/80/90/95, dims]
    levels = np.array(noise_eval.COVERAGE_LEVELS)[:, None]
    n_test = kitti_cv.model("hetero-t").folds[0].n_test  # the held-out errors of fold 0 (~6,950)
    # a calibrated model's coverage is binomial(n_test, level) / n_test: 99 % of it within 2.576 standard deviations
    sampling = 2.576 * np.sqrt(levels * (1 - levels) / n_test)
    assert n_test > 6000
    assert np.all(np.abs(cov[1:] - levels[1:]) <= CALIBRATION_POINTS + sampling[1:])  # 80, 90 and 95 %, both dims
    # the 50 % interval is narrow by 2-5 points (the assets' README)
    assert np.all(np.abs(cov[0] - 0.5) <= 0.045 + sampling[0])
    assert np.all(kitti_cv.model("hetero-t").mean("ice") < 0.03)
    # the homoscedastic baseline over-covers near obstacles and under-covers far ones
    band = kitti_cv.model("homo-normal").band_coverage(0.9)
    assert band[0, 0] > 0.97 and band[-1, 0] < 0.85


def test_kitti_tables_have_one_row_per_model_and_fold(kitti_cv) -> None:
    md = noise_eval.format_markdown(kitti_cv)
    assert "| **hetero-t** |" in md and "| homo-normal |" in md
    lines = noise_eval.format_csv(kitti_cv).strip().splitlines()
    assert len(lines) == 1 + 3
    row = dict(zip(lines[0].split(","), lines[1].split(","), strict=True))
    assert float(row["nll"]) == pytest.approx(kitti_cv.model("homo-normal").folds[0].nll, abs=1e-6)


def test_shipped_noise_pem_grows_with_range() -> None:
    model = pem.load_noise_pem()
    assert model.name == "hetero-t" and model.family == "student-t"
    assert noise_pem_path().stat().st_size < 20_000
    assert model.metadata["command"] == "pemviz pem train --model hetero-t --seed 0 --epochs 100"
    _, log_scale = model.noise_params(model.features(_raw(np.array([10.0, 40.0]))))
    ratio = np.exp(log_scale[1] - log_scale[0])
    assert 4.0 < ratio[0] < 16.0  # range: between z (constant relative error) and z^2 (constant pixel error)
    assert 3.0 < ratio[1] < 5.0  # lateral: about z


# ----------------------------------------------------------------------------------- files, NoisyPEM


@pytest.fixture(scope="module")
def noisy() -> pem.NoisyPEM:
    return pem.NoisyPEM(detect=pem.load_pem("ml-nn"), noise=pem.load_noise_pem())


def test_noise_files_round_trip(tmp_path: Path) -> None:
    models = [pem.load_noise_pem(), _homo("student-t", [3.0, 5.0]), _homo("normal")]
    x = models[1].features(_raw(np.linspace(2, 70, 30)))
    errors = np.random.default_rng(0).normal(0, 1, (30, 2))
    for i, model in enumerate(models):
        back = pem.load_noise_pem(save_noise_pem(model, tmp_path / f"n{i}.pt"))
        assert type(back) is type(model) and back.name == model.name and back.family == model.family
        np.testing.assert_array_equal(back.log_prob(x, errors), model.log_prob(x, errors))


def test_noisy_pem_round_trips_and_scores_detection_and_noise(noisy, tmp_path: Path) -> None:
    back = pem.load_noisy_pem(pem.save_noisy_pem(noisy, tmp_path / "p.pt"))
    x = noisy.features(_raw(np.array([8.0, 25.0, 60.0])))
    detected = np.array([True, False, True])
    errors = np.array([[0.1, 0.01], [np.nan, np.nan], [-3.0, 0.2]])
    logit = noisy.detect.logit_features(x)
    expected = np.array(
        [
            -math.log1p(math.exp(-logit[0])) + noisy.noise.log_prob(x[:1], errors[:1])[0],
            -math.log1p(math.exp(logit[1])),
            -math.log1p(math.exp(-logit[2])) + noisy.noise.log_prob(x[2:], errors[2:])[0],
        ]
    )
    np.testing.assert_allclose(noisy.log_prob(x, detected, errors), expected, rtol=1e-12)
    np.testing.assert_array_equal(back.log_prob(x, detected, errors), noisy.log_prob(x, detected, errors))
    assert back.name == "ml-nn+hetero-t"


def test_noisy_pem_samples_detections_at_the_pem_rate_and_no_error_when_missed(noisy) -> None:
    x = noisy.features(_raw(np.full(40000, 30.0), occ=2))
    p = float(special.expit(noisy.logit(x[:1]))[0])
    detected, errors = noisy.sample(x, np.random.default_rng(0))
    sd = math.sqrt(p * (1 - p) / x.shape[0])
    assert abs(detected.mean() - p) < 4 * sd
    assert np.all(errors[~detected] == 0.0) and np.all(errors[detected] != 0.0)


def test_noisy_pem_rejects_heads_with_different_encodings() -> None:
    with pytest.raises(ValueError, match="encode the salient variables differently"):
        pem.NoisyPEM(detect=pem.load_pem("ml-nn"), noise=_homo("normal"))


@pytest.mark.parametrize(
    ("content", "loader", "message"),
    [
        (b"not a torch file", pem.load_noise_pem, "not a readable noise PEM file"),
        ("detection", pem.load_noise_pem, "not a pemviz noise PEM file (missing format tag 'pemviz-noise-pem')"),
        ("noise", pem.load_noisy_pem, "not a pemviz perception model file"),
        (b"\x00\x01", pem.load_noisy_pem, "not a readable perception model file"),
    ],
)
def test_a_bad_file_gives_one_line_naming_it(tmp_path: Path, content, loader, message) -> None:
    path = tmp_path / "bad.pt"
    if content == "detection":
        pem.save_pem(pem.load_pem("ml-nn"), path)
    elif content == "noise":
        save_noise_pem(pem.load_noise_pem(), path)
    else:
        path.write_bytes(content)
    with pytest.raises(PemFormatError) as info:
        loader(path)
    text = str(info.value)
    assert message in text and str(path) in text and "\n" not in text


def test_unknown_noise_pem_name_lists_the_shipped_ones() -> None:
    with pytest.raises(FileNotFoundError, match="hetero-t"):
        pem.load_noise_pem("hetero-x")


# ------------------------------------------------------------------------------------- label reader

_ROW = st.tuples(
    st.integers(1, 1200),
    st.integers(1, 370),
    st.integers(1, 400),
    st.integers(2, 370),  # detected box
    st.integers(-50, 50),
    st.integers(-50, 50),
    st.integers(-50, 50),
    st.integers(-50, 50),  # errors
)


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(rows=st.lists(st.tuples(st.booleans(), _ROW), min_size=1, max_size=20), header=st.booleans())
def test_label_table_reader_round_trips_or_names_the_bad_line(tmp_path: Path, rows, header) -> None:
    table = np.array([[1.0, *r] if det else [0.0] * 9 for det, r in rows])
    path = tmp_path / "labels.txt"
    text = "".join(" ".join(f"{v:.0f}" for v in row) + "\n" for row in table)
    path.write_text(("# Format: <Detected> ...\n" if header else "") + text)
    det = table[:, 0] == 1
    bad = det & np.any(np.concatenate([table[:, 3:5], table[:, 3:5] - table[:, 7:9]], axis=1) <= 0, axis=1)
    if bad.any():
        line = int(np.flatnonzero(bad)[0]) + 1 + int(header)
        with pytest.raises(data.DataFormatError, match=f"line {line}: a detected obstacle's box"):
            data.load_salient_label_table(path)
    else:
        np.testing.assert_array_equal(data.load_salient_label_table(path), table)


# ------------------------------------------------------------------------------------------------ CLI


def test_cli_trains_a_noise_pem_that_loads(salient, tmp_path: Path, capsys) -> None:
    out = tmp_path / "noise.pt"
    rc = cli_main(
        [
            "pem",
            "train",
            "--model",
            "hetero-t",
            "--epochs",
            "2",
            "--out",
            str(out),
            "--no-progress",
            "--data-dir",
            str(SHARED_DATA),
        ]
    )
    assert rc == 0
    model = pem.load_noise_pem(out)
    assert model.metadata["command"] == "pemviz pem train --model hetero-t --seed 0 --epochs 2"
    assert "NLL on the full training set" in capsys.readouterr().out


def test_cli_eval_reports_the_noise_table(salient, tmp_path: Path, capsys) -> None:
    rc = cli_main(
        [
            "pem",
            "eval",
            "--quick",
            "--models",
            "homo-normal,hetero-t",
            "--out",
            str(tmp_path),
            "--data-dir",
            str(SHARED_DATA),
        ]
    )
    assert rc == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["pem-eval.md", "pem-noise-eval.csv"]
    assert "Noise PEM cross-validation" in (tmp_path / "pem-eval.md").read_text()
    assert "best noise PEM by mean NLL: hetero-t" in capsys.readouterr().out


def test_cli_eval_rejects_bad_noise_epochs(tmp_path: Path, capsys) -> None:
    assert cli_main(["pem", "eval", "--quick", "--noise-epochs", "0", "--out", str(tmp_path)]) == 2
    assert "epochs = 0" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("family", ["normal", "laplace", "student-t"])
def test_the_closed_form_quantile_and_log_density_are_scipy_stats(family):
    """The error families' quantile and log density in closed form (scipy.special) against scipy.stats' frozen
    distributions (the oracle), deep into both tails, per component's degrees of freedom."""
    from pemviz.core.detector_noise import standard_log_density, standard_quantile
    from scipy import stats

    df = np.array([2.5, 7.0]) if family == "student-t" else None
    u = np.array([1e-12, 1e-6, 0.01, 0.3, 0.5, 0.7, 0.99, 1 - 1e-6, 1 - 1e-12])[:, None] * np.ones(2)
    z = np.array([-40.0, -5.0, -1.0, -0.1, 0.0, 0.3, 2.0, 8.0, 60.0])[:, None] * np.ones(2)
    oracle = {"normal": stats.norm(), "laplace": stats.laplace(), "student-t": stats.t(df)}[family]
    np.testing.assert_allclose(standard_quantile(family, df, u), oracle.ppf(u), rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(standard_log_density(family, df, z), oracle.logpdf(z), rtol=1e-12, atol=1e-12)
    with pytest.raises(ValueError, match="unknown error family 'cauchy'"):
        standard_quantile("cauchy", None, u)
