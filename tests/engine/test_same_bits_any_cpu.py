"""A seed gives the same rollouts, bit for bit, with and without numpy's AVX-512 loops: the scene's signals, the
detections, the measurement errors and their log-likelihoods under the target and the proposal (numpy's AVX-512
``log``, ``exp``, ``arctan2`` and SVML ``log1p``, ``power`` round otherwise than libm, which CPUs without AVX-512 run;
pemviz.core.libm)."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from conftest import REPO, load_script

rp = load_script(REPO / "benchmarks" / "fingerprint.py")

CROSSING = dict(
    scenario="crossing", n_per_stage=60, n_stages=2, n_final=60, pretrain_rollouts=20, plain_fallback=0, seed=1
)
"""A short adaptive crossing run: pretraining, 2 cross-entropy stages whose proposal has an error head (it shifts the
measurement errors inside its window), a final batch."""

CUT_IN = dict(scenario="cut-in", method="mc", n_per_stage=300, seed=0)
"""Plain Monte Carlo of the cut-in: its simulator's alpha (``atan2``) and IDM (``pow``) feed the signals, the PEMs'
rows and, through the ego's speed, every later step."""

WITHOUT_AVX512 = rp.DISPATCH_SETTINGS["numpy without AVX-512"]["NPY_DISABLE_CPU_FEATURES"]

CHILD = (
    f"import sys\nsys.path.insert(0, {str(REPO / 'benchmarks')!r})\n"
    + """
import hashlib, json, sys
import numpy as np
from pemviz.config import ExperimentConfig
from pemviz.engine.events import RolloutChunk
from pemviz.engine.experiment import Experiment
from pemviz.scenarios.problems import problem_for
from fingerprint import numpy_dispatch

cfg = ExperimentConfig.of(**json.loads(sys.argv[1]))
digests = {k: hashlib.sha256() for k in ("observations", "detected", "noise", "log_p", "log_q")}
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
)


def rollouts_in_subprocess(config: dict, env: dict[str, str]) -> dict:
    """The sha256 of each event array of the run ``config`` (in chunk order), their sizes and the numpy targets in
    use, from a fresh process started with ``env`` added (numpy reads its dispatch at import)."""
    proc = subprocess.run(
        [sys.executable, "-c", CHILD, json.dumps(config)],
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
@pytest.mark.parametrize("config", [CROSSING, CUT_IN], ids=["crossing-adaptive", "cut-in-mc"])
def test_a_run_has_the_same_bits_with_and_without_numpy_s_avx512_loops(config):
    found = rollouts_in_subprocess(config, {})
    without = rollouts_in_subprocess(config, {"NPY_DISABLE_CPU_FEATURES": WITHOUT_AVX512})
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


def test_atan2_and_power_give_python_s_math_bits():
    # math.atan2 and math.pow call the C library's: pemviz.core.libm must give those bits over the cut-in's ranges
    # (lateral offsets and ranges in metres; speed over set speed, delta 4 and others), the signs and edges included
    import math

    import numpy as np
    from pemviz.core import libm

    rng = np.random.default_rng(1)
    y = np.concatenate([rng.uniform(-15.0, 15.0, 30_000), rng.normal(0.0, 1e-3, 1_000), [0.0, -0.0, 1.0, -1.0, np.inf]])
    x = np.concatenate([rng.uniform(-60.0, 250.0, 30_000), rng.uniform(-1.0, 1.0, 1_000), [-0.0, -1.0, 0.0, -0.0, 1.0]])
    bits = lambda a: np.asarray(a, dtype=np.float64).view(np.int64).tolist()  # noqa: E731 (signed zeros too)
    assert bits(libm.atan2(y, x)) == bits([math.atan2(a, b) for a, b in zip(y, x, strict=True)])
    assert libm.atan2(3.0, 4.0).shape == () and libm.atan2(np.ones((2, 3)), 1.0).shape == (2, 3)
    v = np.concatenate([rng.uniform(0.0, 2.0, 30_000), [0.0, 1.0, 0.5]])
    for delta in (4.0, 3.0, 2.5):
        assert bits(libm.power(v, delta)) == bits([math.pow(a, delta) for a in v])
    assert libm.power(v.reshape(-1, 3), 4.0).shape == (v.size // 3, 3)


LOGSUMEXP_CHILD = """
import json, sys
import numpy as np
from scipy.special import logsumexp
rng = np.random.default_rng(2)
a = rng.normal(-30.0, 5.0, (3, 4000))
print(json.dumps({"axis0": logsumexp(a, axis=0).tolist(), "axis1": logsumexp(a.T, axis=1).tolist(),
                  "all": float(logsumexp(a[:, :50]))}))
"""


def test_logsumexp_gives_scipy_s_bits_without_avx512_and_math_s_sums():
    # a mixture's log density (3 components, 4,000 rollouts): scipy.special.logsumexp in a process without numpy's
    # AVX-512 loops (the bits CPUs without AVX-512 give) is pemviz.core.libm's here, bit for bit; where AVX-512 loops
    # run, scipy's own differs on some columns here (the reason for libm's); and each column is math's
    # log1p(s) + log(1) + max with s summed in numpy's order for 2 terms (s = e_1 + e_2, the maximum left out)
    import math

    import numpy as np
    from pemviz.core import libm
    from scipy.special import logsumexp

    a = np.random.default_rng(2).normal(-30.0, 5.0, (3, 4000))
    proc = subprocess.run(
        [sys.executable, "-c", LOGSUMEXP_CHILD],
        capture_output=True,
        text=True,
        env={**os.environ, "NPY_DISABLE_CPU_FEATURES": WITHOUT_AVX512},
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    avx2 = json.loads(proc.stdout)
    assert libm.logsumexp(a, axis=0).tolist() == avx2["axis0"]
    assert libm.logsumexp(a.T, axis=1).tolist() == avx2["axis1"]
    assert libm.logsumexp(a[:, :50]) == avx2["all"]
    if avx512_in_use():
        assert logsumexp(a, axis=0).tolist() != avx2["axis0"]
    for column in a.T[:500].tolist():
        top = max(column)
        rest = [math.exp(v - top) for v in column if v != top]
        assert libm.logsumexp(np.array(column)) == math.log1p(rest[0] + rest[1]) + math.log(1.0) + top
    edges = libm.logsumexp(np.array([[-np.inf, -np.inf], [np.inf, 1.0], [3.0, 3.0]]), axis=1)
    assert edges.tolist() == [-np.inf, np.inf, 3.0 + math.log(2.0)]
