"""A seed gives the same run whatever the chunk size, the executor and the CPU's kernel dispatch (the contract of
pemviz.studies.reproducibility, which the user guide's Reproducibility section states)."""

from __future__ import annotations

import platform

import pytest

from pemviz.config import ExperimentConfig
from pemviz.studies import reproducibility as rp

SMALL = ["--k", "3", "--n", "100", "--n-final", "300", "--plain-fallback", "0"]
"""A short default run: pretraining, 3 CE stages of 100, a final batch of 300 (the default sampler's stages alone: the
plain Monte Carlo after them has its own chunking test, tests/estimators/test_fallback.py)."""
SMALL_CUT_IN = ["--scenario", "cut-in", "--k", "2", "--n", "150", "--n-final", "200", "--pretrain", "100"]
SMALL_CUT_IN += ["--plain-fallback", "0"]  # the stages alone, as SMALL


def small(scenario: str = "braking", **fields) -> ExperimentConfig:
    # the stages alone: the plain Monte Carlo after them has its own chunking test (tests/estimators/test_fallback.py)
    base = (
        dict(n_stages=3, n_per_stage=100, n_final=300, plain_fallback=0)
        if scenario == "braking"
        else dict(n_stages=2, n_per_stage=150, n_final=200, pretrain_rollouts=100, plain_fallback=0)
    )
    return ExperimentConfig.of(scenario=scenario, **{**base, **fields})


@pytest.mark.parametrize("scenario", ["braking", "cut-in"])
def test_any_chunk_size_gives_the_run_of_whole_batches_bit_for_bit(scenario):
    whole = rp.fingerprint(small(scenario))
    for chunk in (64, 1000):
        got = rp.fingerprint(small(scenario, chunk_rollouts=chunk))
        assert rp.compare(whole, got, same_machine=True) == []
        stages = len(got["stages"])
        # chunks of 64 really cut every stage of more than 64 rollouts; 1,000 cuts none of these stages
        assert got["chunks"] > stages if chunk == 64 else got["chunks"] == whole["chunks"]
    assert whole["failures"] > 0  # the runs found failures: the fingerprints hash real draws


def test_the_comparison_names_what_differs():
    a = {
        "rollouts": "x",
        "stages": [[1, "0.0", 3, 3]],
        "failures": 3,
        "n": 10,
        "summary": "s",
        "log_mu_hat": -30.0,
        "ess": 5.0,
    }
    assert rp.compare(a, dict(a), same_machine=True) == []
    b = {**a, "log_mu_hat": -30.0 * (1 + 5e-13)}
    assert rp.compare(a, b, same_machine=True) == [f"log_mu_hat: -30.0 != {b['log_mu_hat']!r}"]
    assert rp.compare(a, b, same_machine=False) == []
    c = {**a, "log_mu_hat": -30.0 * (1 + 5e-12), "rollouts": "y"}
    assert [d.split(":")[0] for d in rp.compare(a, c, same_machine=False)] == ["rollouts", "log_mu_hat"]


x86 = pytest.mark.skipif(
    platform.machine() not in ("x86_64", "AMD64"), reason="the dispatch settings name x86-64 kernels"
)


@x86
@pytest.mark.parametrize(
    ("args", "settings"),
    [
        (SMALL, list(rp.DISPATCH_SETTINGS)),
        (SMALL_CUT_IN, list(rp.DISPATCH_SETTINGS)),
    ],
    ids=["braking", "cut-in"],
)
def test_every_dispatch_setting_gives_the_same_rollouts_and_printed_numbers(args, settings):
    # each setting picks the kernels another x86-64 CPU would run (AVX2 without AVX-512, scalar torch, MKL's SSE4.2
    # path, OpenBLAS's Haswell or Sandybridge kernels, numpy without its AVX-512 loops): the same rollouts, elites,
    # thresholds and printed line; log mu_hat to 1e-12 relative
    found = rp.fingerprint_in_subprocess(args, {})
    assert found["failures"] > 0
    for name in settings:
        if name == "as found":
            continue
        env = rp.DISPATCH_SETTINGS[name]
        got = rp.fingerprint_in_subprocess(args, env)
        assert_took_effect(env, found["dispatch"], got["dispatch"])
        assert rp.compare(found, got, same_machine=False) == [], name


def assert_took_effect(env: dict[str, str], before: dict, after: dict) -> None:
    """The setting changed the kernels it names (a setting that took no effect would test nothing): torch runs the
    capability asked for (or a lower one the CPU lacks a higher of), numpy none of the targets disabled, OpenBLAS the
    core type asked for."""
    if "ATEN_CPU_CAPABILITY" in env:
        asked = env["ATEN_CPU_CAPABILITY"].upper()
        assert after["torch"] == asked or (asked == "AVX2" and before["torch"] == after["torch"] != "AVX512"), after
    for target in env.get("NPY_DISABLE_CPU_FEATURES", "").split():
        assert target not in after["numpy"], (target, after)
    if "OPENBLAS_CORETYPE" in env:
        assert after["openblas"] == [env["OPENBLAS_CORETYPE"]] or not before["openblas"], after


def test_the_numpy_settings_name_what_this_numpy_dispatches():
    dispatch, in_use = rp.numpy_dispatch()
    assert set(in_use) <= set(dispatch)
    lowest = rp.DISPATCH_SETTINGS["all at their lowest"]["NPY_DISABLE_CPU_FEATURES"].split()
    assert lowest == dispatch  # every dispatched target off: numpy's baseline loops alone
    without = rp.DISPATCH_SETTINGS["numpy without AVX-512"]["NPY_DISABLE_CPU_FEATURES"].split()
    assert set(without) <= set(dispatch) and not any("AVX2" in n or n == "X86_V3" for n in without)


def test_cut_in_chunks_of_1000_give_the_default_chunk_s_rollouts_bit_for_bit():
    """8,192 cut-in rollouts (one default chunk: 40,960 object rows the PEM is asked about at once) and the same seed
    in chunks of 1,000 (blocks of rows that fall elsewhere, remainders of every size): the same measurement errors,
    log p and observations, bit for bit. The PEM networks compute each row on its own (GridMLP); with float64 BLAS
    products, chunks of 1,000 gave other last bits."""
    import numpy as np

    from pemviz.scenarios.problems import problem_for
    from pemviz.core.rollouts import RolloutBatch

    pb = problem_for(ExperimentConfig.of(scenario="cut-in"))

    def rollouts(chunk: int) -> RolloutBatch:
        return RolloutBatch.concatenate(
            list(pb.stream(8192, pb.target, pb.target, np.random.default_rng(0), chunk_size=chunk, keep_rows=False))
        )

    whole, parts = rollouts(8192), rollouts(1000)
    for name in ("noise", "log_p", "observations", "detected"):
        np.testing.assert_array_equal(getattr(parts, name), getattr(whole, name), err_msg=name)
