"""A seed gives the same rollouts, bit for bit, with and without numpy's AVX-512 loops: the detections, the measurement
errors and their log-likelihoods under the target and the proposal (numpy's AVX-512 ``log``, ``exp`` and SVML
``log1p`` round otherwise than libm, which CPUs without AVX-512 run; pemviz.core.libm)."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest
from pemviz.studies import reproducibility as rp

CROSSING = dict(
    scenario="crossing", n_per_stage=60, n_stages=2, n_final=60, pretrain_rollouts=20, plain_fallback=0, seed=1
)
"""A short adaptive crossing run: pretraining, 2 cross-entropy stages whose proposal has an error head (it shifts the
measurement errors inside its window), a final batch."""

WITHOUT_AVX512 = rp.DISPATCH_SETTINGS["numpy without AVX-512"]["NPY_DISABLE_CPU_FEATURES"]

CHILD = """
import hashlib, json, sys
import numpy as np
from pemviz.config import ExperimentConfig
from pemviz.engine.events import RolloutChunk
from pemviz.engine.experiment import Experiment
from pemviz.scenarios.problems import problem_for
from pemviz.studies.reproducibility import numpy_dispatch

cfg = ExperimentConfig.of(**json.loads(sys.argv[1]))
digests = {k: hashlib.sha256() for k in ("detected", "noise", "log_p", "log_q")}
sizes = dict.fromkeys(digests, 0)

def listen(event):
    if isinstance(event, RolloutChunk):
        for k, h in digests.items():
            a = getattr(event.batch, k)
            if a is None:
                continue
            h.update(np.ascontiguousarray(a).tobytes())
            sizes[k] += a.size

Experiment(cfg, [listen], problem=problem_for(cfg)).run()
print(json.dumps({"digests": {k: h.hexdigest() for k, h in digests.items()}, "sizes": sizes,
                  "numpy": numpy_dispatch()[1]}))
"""


def rollouts_in_subprocess(env: dict[str, str]) -> dict:
    """The sha256 of each event array of ``CROSSING`` (in chunk order), their sizes and the numpy targets in use, from
    a fresh process started with ``env`` added (numpy reads its dispatch at import)."""
    proc = subprocess.run(
        [sys.executable, "-c", CHILD, json.dumps(CROSSING)],
        capture_output=True,
        text=True,
        env={**os.environ, **env},
        timeout=900,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    return json.loads(proc.stdout.strip().splitlines()[-1])


def avx512_in_use() -> list[str]:
    """The numpy targets in use here that the setting ``numpy without AVX-512`` turns off."""
    return sorted(set(rp.numpy_dispatch()[1]) & set(WITHOUT_AVX512.split()))


@pytest.mark.skipif(
    not avx512_in_use(), reason="numpy runs no AVX-512 loops on this CPU: both runs would take the same loops"
)
def test_a_crossing_run_has_the_same_bits_with_and_without_numpy_s_avx512_loops():
    found = rollouts_in_subprocess({})
    without = rollouts_in_subprocess({"NPY_DISABLE_CPU_FEATURES": WITHOUT_AVX512})
    assert set(found["numpy"]) >= set(avx512_in_use()) and not set(without["numpy"]) & set(WITHOUT_AVX512.split())
    assert found["sizes"] == without["sizes"] and min(found["sizes"].values()) > 0, found["sizes"]
    assert found["digests"] == without["digests"]


def test_the_libm_functions_give_python_s_math_bits():
    # Python's math module calls the C library's log, exp and log1p: pemviz.core.libm must give those bits on every
    # value, the edges included (numpy's AVX-512 loops differ on a few per cent of these)
    import math

    import numpy as np
    from pemviz.core import libm

    rng = np.random.default_rng(0)
    positive = np.concatenate([rng.uniform(0.0, 1.0, 20_000), np.exp(rng.uniform(-700.0, 700.0, 20_000)), [5e-324]])
    assert libm.log(positive).tolist() == [math.log(v) for v in positive]
    x = np.concatenate([rng.uniform(-745.0, 709.0, 20_000), rng.normal(0.0, 3.0, 20_000)])
    assert libm.exp(x).tolist() == [math.exp(v) for v in x]
    t = np.concatenate([rng.uniform(-1.0, 1.0, 20_000), np.exp(rng.uniform(-40.0, 40.0, 20_000))])
    assert libm.log1p(t).tolist() == [math.log1p(v) for v in t]
    with np.errstate(all="ignore"):
        edges = (
            libm.log(np.array([0.0, -1.0, np.inf])),
            libm.exp(np.array([-800.0, 800.0])),
            libm.log1p(np.array([-1.0])),
        )
    assert edges[0][0] == -np.inf and np.isnan(edges[0][1]) and edges[0][2] == np.inf
    assert edges[1].tolist() == [0.0, np.inf] and edges[2].tolist() == [-np.inf]
    u = np.array([0.25, 0.5])
    assert libm.log(u, out=u) is u and u.tolist() == [math.log(0.25), math.log(0.5)]
