"""A seed gives the same run whatever the chunk size, the executor and the CPU's kernel dispatch (the contract of
benchmarks/fingerprint.py, which the user guide's Reproducibility section states)."""

from __future__ import annotations

import functools
import json
import os
import platform
import subprocess
import sys

import pytest
from pemviz.config import ExperimentConfig

from conftest import REPO, load_script

rp = load_script(REPO / "benchmarks" / "fingerprint.py")

BRAKING = dict(n_stages=3, n_per_stage=100, n_final=300, plain_fallback=0)
"""A short default run: pretraining, 3 CE stages of 100, a final batch of 300 (the default sampler's stages alone: the
plain Monte Carlo after them has its own chunking test, tests/estimators/test_fallback.py)."""
CUT_IN = dict(n_stages=2, n_per_stage=60, n_final=60, pretrain_rollouts=40, plain_fallback=0)
"""The stages alone, as BRAKING: 2 CE stages of 60 whose thresholds differ (0.101, then 0.0093), 39 failures in the
final 60 (seed 0)."""


def small(scenario: str = "braking", **fields) -> ExperimentConfig:
    base = BRAKING if scenario == "braking" else CUT_IN
    return ExperimentConfig.of(scenario=scenario, **{**base, **fields})


@functools.cache
def serial(scenario: str) -> dict:
    """:func:`rp.fingerprint` of ``small(scenario)`` run serially in this process, in whole batches: the reference
    of the chunk-size and the dispatch tests (one run each, read by both)."""
    return rp.fingerprint(small(scenario, executor="serial"))


@pytest.mark.parametrize("scenario", ["braking", "cut-in"])
def test_any_chunk_size_gives_the_run_of_whole_batches_bit_for_bit(scenario):
    # chunks of 32 cut every stage (40, 60, 100, 300 rollouts) with a remainder, simulated by the local executor's
    # workers; the whole batches are the serial run in this process (`serial`), so chunking and executor both change
    whole = serial(scenario)
    got = rp.fingerprint(small(scenario, chunk_rollouts=32))
    assert rp.compare(whole, got, same_machine=True) == []
    assert got["chunks"] > len(got["stages"]) and whole["chunks"] == len(whole["stages"])
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


def fingerprints_in_subprocess(env: dict[str, str]) -> dict[str, dict]:
    """scenario -> :func:`rp.fingerprint` of the braking and the cut-in run (``small``, serial as the module's command
    line runs them), both in one fresh process started with ``env`` added (the dispatch is read at start-up)."""
    code = (
        "import json, sys\n"
        "from pemviz.config import ExperimentConfig\n"
        "from pemviz.engine.executors import close_executors\n"
        f"sys.path.insert(0, {str(REPO / 'benchmarks')!r})\n"
        "from fingerprint import fingerprint\n"
        "runs = json.loads(sys.argv[1])\n"
        "out = {s: fingerprint(ExperimentConfig.of(scenario=s, executor='serial', **f)) for s, f in runs.items()}\n"
        "close_executors()\n"
        "print(json.dumps(out))\n"
    )
    runs = json.dumps({"braking": BRAKING, "cut-in": CUT_IN})
    proc = subprocess.run(
        [sys.executable, "-c", code, runs], capture_output=True, text=True, env={**os.environ, **env}, timeout=1800
    )
    assert proc.returncode == 0, (env, proc.stderr[-2000:])
    return json.loads(proc.stdout.strip().splitlines()[-1])


def dispatch_runs(settings: dict[str, dict[str, str]]) -> list[tuple[list[str], dict[str, str]]]:
    """The settings (but ``as found``) merged into as few processes as their variables allow: a setting joins the first
    run whose variables it does not set otherwise (the most variables first). Each run's kernels are those of the
    settings it holds; a setting whose rounding differed would differ within its run as it does alone."""
    runs: list[tuple[list[str], dict[str, str]]] = []
    for name, env in sorted(settings.items(), key=lambda kv: -len(kv[1])):
        if not env:
            continue
        for names, run in runs:
            if all(run.get(k, v) == v for k, v in env.items()):
                names.append(name)
                run.update(env)
                break
        else:
            runs.append(([name], dict(env)))
    return runs


def test_the_settings_merge_into_two_runs_that_set_each_one_s_variables():
    runs = dispatch_runs(rp.DISPATCH_SETTINGS)
    assert sorted(n for names, _ in runs for n in names) == sorted(n for n in rp.DISPATCH_SETTINGS if n != "as found")
    for names, run in runs:
        for name in names:
            assert rp.DISPATCH_SETTINGS[name].items() <= run.items(), (name, run)
    assert [names[0] for names, _ in runs] == ["all at their lowest", "torch without AVX-512"]
    assert runs[1][1]["ATEN_CPU_CAPABILITY"] == "avx2" and runs[1][1]["OPENBLAS_CORETYPE"] == "Haswell"


@x86
def test_every_dispatch_setting_gives_the_same_rollouts_and_printed_numbers():
    # each setting picks the kernels another x86-64 CPU would run (AVX2 without AVX-512, scalar torch, MKL's SSE4.2
    # path, OpenBLAS's Haswell or Sandybridge kernels, numpy without its AVX-512 loops): the same rollouts, elites,
    # thresholds and printed line; log mu_hat to 1e-12 relative. Both scenarios run in each process; the settings
    # share two processes (:func:`dispatch_runs`: all at their lowest, all at AVX2); as found is this process's own
    # serial run (`serial`, also the chunk-size test's reference).
    found = {scenario: serial(scenario) for scenario in ("braking", "cut-in")}
    assert all(f["failures"] > 0 for f in found.values())
    for names, env in dispatch_runs(rp.DISPATCH_SETTINGS):
        got = fingerprints_in_subprocess(env)
        for scenario in ("braking", "cut-in"):
            assert_took_effect(env, found[scenario]["dispatch"], got[scenario]["dispatch"])
            assert rp.compare(found[scenario], got[scenario], same_machine=False) == [], (names, scenario)


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
    """2,001 cut-in rollouts in one default chunk (10,005 object rows the PEM is asked about at once) and the same seed
    in chunks of 1,000 (blocks of rows that fall elsewhere, and a last chunk of one rollout): the same measurement
    errors, log p and observations, bit for bit. The PEM networks compute each row on its own (GridMLP); with float64
    BLAS products, chunks of 1,000 gave other last bits than the default chunk."""
    import numpy as np
    from pemviz.core.lockstep import DEFAULT_CHUNK_SIZE
    from pemviz.core.rollouts import RolloutBatch
    from pemviz.scenarios.problems import problem_for

    pb = problem_for(ExperimentConfig.of(scenario="cut-in"))

    def rollouts(chunk: int) -> tuple[RolloutBatch, int]:
        rng = np.random.default_rng(0)
        chunks = list(pb.stream(2001, pb.target, pb.target, rng, chunk_size=chunk, keep_rows=False))
        return RolloutBatch.concatenate(chunks), len(chunks)

    (whole, one), (parts, three) = rollouts(DEFAULT_CHUNK_SIZE), rollouts(1000)
    assert (one, three) == (1, 3)
    for name in ("noise", "log_p", "observations", "detected"):
        np.testing.assert_array_equal(getattr(parts, name), getattr(whole, name), err_msg=name)
