"""What a seed reproduces, and where: a run's fingerprint under the CPU's vector-dispatch settings, chunk sizes and
executors.

The contract this module checks (:func:`compare`): on one machine any chunk size and executor give the same
fingerprint, bit for bit; on any x86-64 CPU and dispatch setting (:data:`DISPATCH_SETTINGS`) the same rollouts,
thresholds, elites and printed numbers, log mu_hat within :data:`LOG_MU_RTOL` relative (:mod:`pemviz.core.exact`).
``python benchmarks/fingerprint.py --help`` runs one; ``benchmarks/reproducibility.py`` the matrix (both outside the
package: they check it)."""

from __future__ import annotations

import argparse
import hashlib
import json
import math
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from pemviz.config import ExperimentConfig


def numpy_dispatch() -> tuple[list[str], list[str]]:
    """(the SIMD targets this numpy build dispatches to at run time, those this process uses): e.g. ``(['X86_V3',
    'X86_V4', 'AVX512_ICL', 'AVX512_SPR'], ['X86_V3'])`` under ``NPY_DISABLE_CPU_FEATURES="X86_V4 AVX512_ICL
    AVX512_SPR"``. numpy names its targets by version (``AVX512F``, ``AVX512_SKX`` before 2.4; ``X86_V4`` since),
    and ignores, with a warning, a name it does not dispatch."""
    from numpy._core import _multiarray_umath as umath  # type: ignore[attr-defined]  # private: not in numpy's stubs

    dispatch = list(getattr(umath, "__cpu_dispatch__", []))
    return dispatch, [name for name in dispatch if umath.__cpu_features__.get(name, False)]


def _numpy_without(keep: str) -> str:
    """``NPY_DISABLE_CPU_FEATURES`` for this numpy: every dispatched target beyond AVX2 (``keep="avx2"``), or every one
    (``keep="baseline"``)."""
    dispatch, _ = numpy_dispatch()
    avx512 = [n for n in dispatch if "AVX512" in n or n in ("X86_V4", "AVX10")]
    return " ".join(avx512 if keep == "avx2" else dispatch)


DISPATCH_SETTINGS: dict[str, dict[str, str]] = {
    "as found": {},
    "torch without AVX-512": {"ATEN_CPU_CAPABILITY": "avx2"},
    "torch scalar": {"ATEN_CPU_CAPABILITY": "default"},
    "MKL SSE4.2": {"MKL_ENABLE_INSTRUCTIONS": "SSE4_2", "MKL_CBWR": "COMPATIBLE"},
    "MKL AVX2": {"MKL_ENABLE_INSTRUCTIONS": "AVX2"},
    "numpy without AVX-512": {"NPY_DISABLE_CPU_FEATURES": _numpy_without("avx2")},
    "OpenBLAS Haswell": {"OPENBLAS_CORETYPE": "Haswell"},
    "all at their lowest": {
        "ATEN_CPU_CAPABILITY": "default",
        "MKL_ENABLE_INSTRUCTIONS": "SSE4_2",
        "MKL_CBWR": "COMPATIBLE",
        "OPENBLAS_CORETYPE": "Sandybridge",
        "NPY_DISABLE_CPU_FEATURES": _numpy_without("baseline"),
    },
}
"""Settings of torch's (``ATEN_CPU_CAPABILITY``), MKL's, numpy's (``NPY_DISABLE_CPU_FEATURES``, by
:func:`numpy_dispatch`'s names) and OpenBLAS's kernel dispatch that any AVX2 x86-64 CPU runs, each another CPU's
kernels; a fingerprint records the ``dispatch`` used."""


def dispatch_in_use() -> dict[str, Any]:
    """What this process's kernels dispatch to: torch's CPU capability, numpy's SIMD targets in use
    (:func:`numpy_dispatch`) and each OpenBLAS's core type (``threadpoolctl``)."""
    import torch
    from threadpoolctl import threadpool_info

    return {
        "torch": torch.backends.cpu.get_cpu_capability(),
        "numpy": numpy_dispatch()[1],
        "openblas": sorted(
            {str(i.get("architecture")) for i in threadpool_info() if i.get("internal_api") == "openblas"}
        ),
    }


LOG_MU_RTOL = 1e-12
"""log mu_hat's relative tolerance across dispatch settings: the last bits of the weights' exp and log."""


def fingerprint(config: ExperimentConfig) -> dict[str, Any]:
    """Run ``config`` (an :class:`pemviz.config.ExperimentConfig`) and return what identifies the run: ``rollouts``
    (sha256 of every stage's detections and failures, in rollout order), ``stages`` ([stage, repr(gamma), elites,
    failures]), ``log_mu_hat`` (nats), ``failures``, ``n``, ``ess``, ``summary`` (the printed verdict line) and
    ``chunks`` (how many chunks the run's stages came in), ``dispatch`` (:func:`dispatch_in_use`)."""
    import numpy as np
    from pemviz.engine.events import RolloutChunk, RolloutsSampled, RunFinished
    from pemviz.engine.experiment import Experiment
    from pemviz.scenarios.problems import problem_for

    digest = hashlib.sha256()
    chunks = [0]

    def listen(event: Any) -> None:
        if isinstance(event, RolloutChunk):
            chunks[0] += 1
            digest.update(np.ascontiguousarray(event.batch.detected).tobytes())
        elif isinstance(event, RolloutsSampled):
            if event.index is None:
                failed = event.failed
            else:
                assert event.stage_robustness is not None  # a sample of the stage comes with every robustness
                failed = event.stage_robustness < 0
            digest.update(np.ascontiguousarray(failed).tobytes())

    problem = problem_for(config)
    result = Experiment(config, [listen], problem=problem).run()
    assert isinstance(result, RunFinished)  # nothing cancels this run
    e = result.final.estimate
    return {
        "rollouts": digest.hexdigest(),
        "stages": [[s.stage, repr(s.gamma), int(s.n_elites), int(s.estimate.n_failures)] for s in result.stages],
        "log_mu_hat": e.log_mu_hat,
        "failures": e.n_failures,
        "n": e.n,
        "ess": e.ess,
        "summary": e.summary(problem.exact_log_p, problem.reference),
        "chunks": chunks[0],
        "dispatch": dispatch_in_use(),
    }


def compare(a: dict[str, Any], b: dict[str, Any], same_machine: bool) -> list[str]:
    """What differs between two fingerprints beyond the contract (module docstring): an empty list when it holds.
    ``same_machine``: every field bit for bit (but the chunk count); otherwise log mu_hat within
    :data:`LOG_MU_RTOL` and ESS within 1e-9 relative."""
    out = [f"{k}: {a[k]!r} != {b[k]!r}" for k in ("rollouts", "stages", "failures", "n", "summary") if a[k] != b[k]]
    if same_machine:
        out += [f"{k}: {a[k]!r} != {b[k]!r}" for k in ("log_mu_hat", "ess") if a[k] != b[k]]
    else:
        if not math.isclose(a["log_mu_hat"], b["log_mu_hat"], rel_tol=LOG_MU_RTOL, abs_tol=0.0):
            out.append(f"log_mu_hat: {a['log_mu_hat']!r} vs {b['log_mu_hat']!r} beyond {LOG_MU_RTOL:g} relative")
        if not math.isclose(a["ess"], b["ess"], rel_tol=1e-9):
            out.append(f"ess: {a['ess']!r} vs {b['ess']!r}")
    return out


def main(argv: list[str] | None = None) -> None:
    """Print one run's :func:`fingerprint` as JSON (the module docstring's command line)."""
    from pemviz.config import ExperimentConfig

    p = argparse.ArgumentParser(prog="python benchmarks/fingerprint.py", description=__doc__.split("\n")[0])
    p.add_argument("--scenario", default="braking")
    p.add_argument("--k", type=int, help="cross-entropy stages K (default: the default config's)")
    p.add_argument("--n", type=int, help="rollouts per stage N")
    p.add_argument("--n-final", type=int, help="rollouts of the final estimate N_e")
    p.add_argument("--pretrain", type=int, help="pretraining rollouts")
    p.add_argument("--chunk", type=int, help="ExperimentConfig.chunk_rollouts")
    p.add_argument("--executor", default="serial")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--plain-fallback", type=int, help="plain_fallback (0: the stages alone)")
    a = p.parse_args(argv)
    fields = {
        "plain_fallback": a.plain_fallback,
        "n_stages": a.k,
        "n_per_stage": a.n,
        "n_final": a.n_final,
        "pretrain_rollouts": a.pretrain,
        "chunk_rollouts": a.chunk,
    }
    cfg = ExperimentConfig.of(
        scenario=a.scenario, executor=a.executor, seed=a.seed, **{k: v for k, v in fields.items() if v is not None}
    )
    try:
        print(json.dumps(fingerprint(cfg)))
    finally:
        from pemviz.engine.executors import close_executors

        close_executors()


if __name__ == "__main__":
    main()
