"""What a run imports. A proposal keeps its parameters in numpy until something needs torch: the same draws, weights,
fits and estimates as a proposal in torch, bit for bit (the seed contract), and torch's own state left alone when it
moves there. A default run imports neither torch nor, as the program, pandas."""

from __future__ import annotations

import numpy as np
import pemviz.core.sampling as sampling
import pytest
import torch
from pemviz.config import ExperimentConfig
from pemviz.core import torch_use
from pemviz.core.sampling import Proposal, StateProposal, fit_proposal
from pemviz.engine.experiment import Experiment
from pemviz.scenarios.problems import build_problem


@pytest.fixture
def numpy_first(monkeypatch):
    """New proposals start in numpy, as in a process that has not imported torch."""
    monkeypatch.setattr(sampling, "torch_imported", lambda: False)


def _pair(make, seed: int = 3):
    """(a proposal in numpy, one in torch), both initialised from ``seed``."""
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(sampling, "torch_imported", lambda: False)
        in_numpy = make()
    in_torch = make()
    in_numpy.initialise(np.random.default_rng(seed))
    in_torch.initialise(np.random.default_rng(seed))
    assert in_numpy._module is None and in_torch._module is not None
    return in_numpy, in_torch


MAKERS = {"gap": lambda: Proposal(12.0), "state": lambda: StateProposal((0, 1, 2), (12.0, 8.0, 1.0), (20.0, 8.0, 0.0))}


@pytest.mark.parametrize("kind", MAKERS)
def test_a_proposal_in_numpy_samples_curves_and_fits_as_one_in_torch(kind):
    """Sampling logits and exact fits: the same bits in numpy as in torch; the curve within float64 rounding of
    torch's log-softmax (it is drawn, not sampled from)."""
    a, b = _pair(MAKERS[kind])
    rng = np.random.default_rng(0)
    obs = np.column_stack([rng.uniform(0, 30, 500), rng.uniform(0, 8, 500), rng.uniform(0, 1, 500)])
    np.testing.assert_array_equal(a.detect_logit(obs), b.detect_logit(obs))
    inputs = obs[:200, : a.n_inputs].reshape(200, -1).squeeze(-1) if kind == "gap" else obs[:200]
    counts = rng.uniform(0, 3, (200, 2))
    la = fit_proposal(a, inputs, counts, 60, 1e-2, per=300.0)
    lb = fit_proposal(b, torch.as_tensor(inputs), torch.as_tensor(counts), 60, 1e-2, per=300.0)
    assert la == lb and a._module is None  # the exact fit never moved it into torch
    for pa, pb in zip(a.parameter_arrays(), b.parameter_arrays(), strict=False):
        np.testing.assert_array_equal(pa, pb)
    np.testing.assert_array_equal(a.detect_logit(obs), b.detect_logit(obs))  # the cache followed the fit
    grid = np.linspace(0.0, 40.0, 81)
    with torch.no_grad():
        h = torch.as_tensor(b._curve_inputs(grid))
        torch_curve = b.forward(h)[:, 1].exp().numpy()
    np.testing.assert_allclose(a.curve(grid), torch_curve, rtol=1e-13, atol=1e-300)
    assert 0.0 < a.curve(grid).min() and a.curve(grid).max() < 1.0


def test_moving_into_torch_keeps_the_parameters_and_torchs_random_state():
    a, _ = _pair(MAKERS["state"])
    before = [p.copy() for p in a.parameter_arrays()]
    state = torch.random.get_rng_state()
    net = a.net
    assert torch.equal(torch.random.get_rng_state(), state)  # its own weights: torch's generator untouched
    assert a._module is not None and a._arrays is None
    for p, q in zip(net.parameters(), before, strict=False):
        assert p.dtype == torch.float64
        np.testing.assert_array_equal(p.detach().numpy(), q)
    assert set(a.state_dict()) == {f"net.{i}.{k}" for i in (0, 2, 4) for k in ("weight", "bias")}


def test_parameters_of_the_wrong_shape_are_refused(numpy_first):
    q = Proposal()
    with pytest.raises(ValueError, match="expected"):
        q.set_parameter_arrays([np.zeros((32, 2))] + [np.zeros(s) for s in q.layer_shapes()[1:]])


def test_a_run_in_numpy_is_the_run_in_torch(numpy_first, monkeypatch):
    """The seed contract: a default-settings braking run whose proposals never enter torch gives the estimate, stage
    by stage, of the same run in torch."""
    problem = build_problem("main")
    cfg = ExperimentConfig.of(n_per_stage=60, n_stages=3, n_final=200, seed=4)
    in_numpy = Experiment(cfg, problem=problem).run()
    monkeypatch.setattr(sampling, "torch_imported", lambda: True)
    in_torch = Experiment(cfg, problem=problem).run()
    a, b = in_numpy.final.estimate, in_torch.final.estimate
    assert a.n_failures > 0 and (a.log_mu_hat, a.n_failures, a.ess) == (b.log_mu_hat, b.n_failures, b.ess)
    for sa, sb in zip(in_numpy.stages, in_torch.stages, strict=False):
        assert sa.estimate.log_mu_hat == sb.estimate.log_mu_hat or (
            np.isnan(sa.estimate.log_mu_hat) and np.isnan(sb.estimate.log_mu_hat)
        )
        np.testing.assert_allclose(sa.proposal_curve, sb.proposal_curve, rtol=1e-13)


def test_a_pending_thread_count_applies_when_torch_is_first_asked_for():
    before = torch.get_num_threads()
    try:
        torch_use.want_threads(1)
        assert torch_use.torch_module() is torch and torch.get_num_threads() == 1
        assert torch_use.settle() == before  # what to restore
        assert torch_use.settle() is None
    finally:
        torch.set_num_threads(before)


@pytest.mark.parametrize("scenario", ["braking", "cut-in"])
def test_a_default_run_with_its_recording_imports_neither_torch_nor_pandas(tmp_path, scenario):
    """torch (about 1 s to import) is not needed by a run whose fits are exact: the PEM, the proposal, the STL
    robustness, the estimate and the recording all run without it; nor is pandas (0.2 s) by the program's recording
    (:func:`pemviz.sinks.process.settle_pyarrow_without_pandas`). A small run of each scene, as the program, in a
    new process (its exit hook prints what was imported). The cut-in's traffic comes from highway-env, which imports
    pandas itself. A braking run loads neither the cut-in's modules, nor splitting's, nor the report's."""
    import subprocess
    import sys

    code = (
        "import os, sys; import pemviz.cli as cli; "
        "others = ('pemviz.scenarios.cut_in', 'pemviz.estimators.ams', 'pemviz.sinks.report'); "
        "exit_now = lambda status: print('unused', [m for m in others if m in sys.modules], 'exit', status, "
        "'torch', 'torch' in sys.modules, 'pandas', 'pandas' in sys.modules, flush=True) or os._exit(status); "
        "cli._exit_now = exit_now; "
        f"sys.argv = ['pemviz', 'run', '--scenario', {scenario!r}, '--k', '2', '--n', '40', '--n-final', '60', "
        f"'--save', {str(tmp_path / 'run.rrd')!r}]; cli.main()"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    pandas = scenario != "braking"
    assert out.stdout.strip().endswith(f"exit 0 torch False pandas {pandas}"), out.stdout[-500:] + out.stderr[-2000:]
    if scenario == "braking":  # nor the other scene's, method's or command's modules
        assert "unused [] exit" in out.stdout
    assert (tmp_path / "run.rrd").stat().st_size > 0


def test_the_pandas_settle_is_the_programs_alone(tmp_path, monkeypatch):
    """pemviz called as a library (``main(argv)``) leaves pyarrow as it found it."""
    import pemviz.sinks.process as process
    from pemviz.cli import main

    def refuse() -> bool:
        raise AssertionError("a library call changed pyarrow's process-wide state")

    monkeypatch.setattr(process, "settle_pyarrow_without_pandas", refuse)
    assert main(["run", "--k", "1", "--n", "20", "--n-final", "20", "--save", str(tmp_path / "r.rrd")]) == 0


def test_after_the_settle_pandas_imports_and_converts_as_before():
    """The settle refuses nothing afterwards: pandas imports, and pyarrow converts its frames (a new process, where
    pandas was not imported)."""
    import subprocess
    import sys

    code = (
        "import sys; from pemviz.sinks.process import settle_pyarrow_without_pandas as settle; "
        "print(settle(), 'pandas' in sys.modules); import pandas as pd, pyarrow as pa; "
        "t = pa.Table.from_pandas(pd.DataFrame({'x': [1.5, None]})); print(t.column('x').to_pylist(), settle())"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.stdout.split("\n")[:2] == ["True False", "[1.5, None] False"], out.stdout + out.stderr[-2000:]


def test_a_checkpoint_loads_into_numpy_with_the_same_weights(tmp_path, numpy_first):
    """A proposal checkpoint (torch's file format) is read without torch into a proposal in numpy: the same
    parameters and sampling logits as the proposal saved."""
    from pemviz.core.sampling import load_proposal, save_proposal

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(sampling, "torch_imported", lambda: True)
        saved = Proposal(7.5)
    saved.initialise(np.random.default_rng(11))
    loaded = load_proposal(save_proposal(saved, tmp_path / "q.proposal.pt"))
    assert loaded._module is None and not loaded.training and loaded.h_scale == 7.5
    for a, b in zip(loaded.parameter_arrays(), saved.parameter_arrays(), strict=False):
        np.testing.assert_array_equal(a, b)
    obs = np.random.default_rng(1).uniform(0, 30, (200, 3))
    np.testing.assert_array_equal(loaded.detect_logit(obs), saved.detect_logit(obs))


def test_the_program_imports_scipy_special_without_numpys_unused_submodules():
    """scipy's array-API shim copies numpy's namespace when scipy.special is imported; as the program, numpy.f2py
    and numpy.testing are left out meanwhile (:func:`pemviz.sinks.process.import_scipy_special_lean`): the shim has
    every name it has otherwise, numpy's among them (read from numpy when first read), numpy's own ``__all__`` and
    ``dir`` are as before, and scipy.special computes as before (new processes)."""
    import json
    import subprocess
    import sys

    probe = (
        "import json, sys, numpy as np; {setup}; import scipy.special as sp; "
        "import scipy._lib.array_api_compat.numpy as shim; "
        "loaded = [m for m in ('numpy.f2py', 'numpy.testing') if m in sys.modules]; "
        "x = np.linspace(-30.0, 30.0, 61); "
        "print(json.dumps({{'loaded': loaded, 'all': sorted(shim.__all__), 'dir': sorted(dir(shim)), "
        "'np_all': sorted(np.__all__), 'np_dir': sorted(dir(np)), "
        "'values': [float(sp.logsumexp(x)), sp.softmax(x).tolist(), sp.expit(x).tolist()], "
        "'same': [getattr(shim, n) is getattr(np, n) for n in ('testing', 'f2py', 'ma', 'random')]}}))"
    )
    lean = "from pemviz.sinks.process import import_scipy_special_lean as lean; assert lean()"
    docs = [
        json.loads(
            subprocess.run(
                [sys.executable, "-c", probe.format(setup=setup)],
                capture_output=True,
                text=True,
                timeout=120,
                check=True,
            ).stdout
        )
        for setup in (lean, "pass")
    ]
    assert docs[0]["loaded"] == [] and docs[1]["loaded"] == ["numpy.f2py", "numpy.testing"]
    for key in ("all", "dir", "np_all", "np_dir", "values", "same"):
        assert docs[0][key] == docs[1][key], key
    assert docs[0]["same"] == [True] * 4


def test_a_default_braking_run_imports_neither_f2py_nor_numpys_test_helpers(tmp_path):
    """The program's run (its recording process aside) never imports numpy.f2py or numpy.testing."""
    import subprocess
    import sys

    code = (
        "import os, sys; import pemviz.cli as cli; "
        "cli._exit_now = lambda status: print('unused', [m for m in ('numpy.f2py', 'numpy.testing') "
        "if m in sys.modules], 'exit', status, flush=True) or os._exit(status); "
        f"sys.argv = ['pemviz', 'run', '--k', '2', '--n', '40', '--n-final', '60', "
        f"'--save', {str(tmp_path / 'run.rrd')!r}]; cli.main()"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert out.stdout.strip().endswith("unused [] exit 0"), out.stdout[-500:] + out.stderr[-2000:]
    assert (tmp_path / "run.rrd").stat().st_size > 0
