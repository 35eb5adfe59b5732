"""The paper's B-NN baseline: a Bayesian PEM fitted by variational inference with pyro (Innes & Ramamoorthy 2022,
Table I: the ML-NN's layers without BatchNorm, N(0, 1) priors, a low-rank multivariate normal guide), predicting the
posterior predictive mean p(detect | x) = E_q[sigmoid(f_w(x))] over ~800 samples, kept in log space
(``logsumexp_s(log sigmoid(+-l_s)) - log S``)."""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np
from scipy.special import expit, log_expit, logsumexp
from tqdm.auto import tqdm

from pemviz.pem.encoding import (
    N_FEATURES,
    NormStats,
    braking_salient_inputs,
    check_features,
    check_training_data,
    encode_salient,
    fit_norm_stats,
)


def _site_shapes(hidden: int) -> dict[str, tuple[int, ...]]:
    return {
        "w1": (N_FEATURES, hidden),
        "b1": (hidden,),
        "w2": (hidden, hidden),
        "b2": (hidden,),
        "w3": (hidden, 1),
        "b3": (1,),
    }


@dataclass(frozen=True, eq=False)
class BayesianPEM:
    """Posterior samples of the B-NN's weights: ``weights[site]`` float64 ``[S, *shape]`` for the sites
    ``w1 [14, H], b1 [H], w2 [H, H], b2 [H], w3 [H, 1], b3 [1]``."""

    kind: ClassVar[str] = "bnn"

    name: str
    norm: NormStats
    weights: Mapping[str, np.ndarray]
    metadata: Mapping[str, Any] = field(default_factory=dict)

    @property
    def n_samples(self) -> int:
        return int(self.weights["w1"].shape[0])

    def features(self, raw_inputs: np.ndarray) -> np.ndarray:
        return encode_salient(raw_inputs, self.norm)

    def sample_logits(self, features: np.ndarray) -> np.ndarray:
        """Per-sample logits float64 ``[S, N]`` for encoded features ``[N, 14]``."""
        w = self.weights
        h = np.maximum(np.einsum("nf,sfh->snh", features, w["w1"]) + w["b1"][:, None, :], 0.0)
        h = np.maximum(np.matmul(h, w["w2"]) + w["b2"][:, None, :], 0.0)
        return (np.matmul(h, w["w3"]) + w["b3"][:, None, :])[..., 0]

    def logit_features(self, features: np.ndarray, *, chunk: int = 256) -> np.ndarray:
        """Logit of the posterior predictive mean p(detect), float64 ``[N]`` (rows in chunks)."""
        x = check_features(features)
        out = np.empty(x.shape[0], dtype=np.float64)
        for start in range(0, x.shape[0], chunk):
            logits = self.sample_logits(x[start : start + chunk])  # [S, n]
            log_p = logsumexp(log_expit(logits), axis=0)
            log_q = logsumexp(log_expit(-logits), axis=0)
            out[start : start + chunk] = log_p - log_q  # the log S terms cancel
        return out

    def logit(self, raw_inputs: np.ndarray) -> np.ndarray:
        """Logit of the posterior predictive mean p(detect) for raw salient inputs ``[N, 11]``."""
        return self.logit_features(encode_salient(raw_inputs, self.norm))

    def logit_at_gap(self, gap_m: np.ndarray) -> np.ndarray:
        """Logit of the predictive mean p(detect) of the braking scenario's lead at ``gap_m`` (same shape)."""
        gap = np.asarray(gap_m, dtype=np.float64)
        return self.logit(braking_salient_inputs(gap)).reshape(gap.shape)

    def prob_at_gap(self, gap_m: np.ndarray) -> np.ndarray:
        return expit(self.logit_at_gap(gap_m))

    def prob(self, raw_inputs: np.ndarray) -> np.ndarray:
        return expit(self.logit(raw_inputs))


def train_bnn_pem(
    inputs: np.ndarray,
    labels: np.ndarray,
    *,
    name: str = "b-nn",
    hidden: int = 20,
    steps: int = 2000,
    batch_size: int = 1024,
    lr: float = 1e-2,
    rank: int = 10,
    n_samples: int = 800,
    seed: int = 0,
    norm: NormStats | None = None,
    progress: bool = False,
) -> BayesianPEM:
    """Fit the B-NN by stochastic variational inference (pyro ``SVI``, ``Trace_ELBO``, mini-batches of
    ``batch_size`` by ``pyro.plate``, ``ClippedAdam`` at ``lr`` decayed 10x over ``steps``, guide
    ``AutoLowRankMultivariateNormal(rank=rank, init_scale=0.01)``), then draw ``n_samples`` weight sets; one torch
    thread, ``pyro.set_rng_seed(seed)``.

    Raises:
        ValueError: mismatched lengths, labels not in {0, 1}."""
    import pyro
    import pyro.distributions as dist
    import torch
    from pyro.infer import SVI, Trace_ELBO
    from pyro.infer.autoguide import AutoLowRankMultivariateNormal

    raw, y = check_training_data(inputs, labels)
    norm = norm if norm is not None else fit_norm_stats(raw)
    x = torch.as_tensor(encode_salient(raw, norm), dtype=torch.float32)
    t = torch.as_tensor(y, dtype=torch.float32)
    shapes = _site_shapes(hidden)
    batch = min(batch_size, x.shape[0])

    def model(x: torch.Tensor, t: torch.Tensor | None = None) -> None:
        w = {k: pyro.sample(k, dist.Normal(0.0, 1.0).expand(s).to_event(len(s))) for k, s in shapes.items()}
        with pyro.plate("data", x.shape[0], subsample_size=batch) as idx:
            h = torch.relu(x[idx] @ w["w1"] + w["b1"])
            h = torch.relu(h @ w["w2"] + w["b2"])
            logit = (h @ w["w3"] + w["b3"]).squeeze(-1)
            pyro.sample("obs", dist.Bernoulli(logits=logit), obs=None if t is None else t[idx])

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        pyro.clear_param_store()
        pyro.set_rng_seed(seed)
        guide = AutoLowRankMultivariateNormal(model, rank=rank, init_scale=0.01)
        optim = pyro.optim.ClippedAdam({"lr": lr, "lrd": 0.1 ** (1.0 / max(steps, 1))})
        svi = SVI(model, guide, optim, Trace_ELBO())
        it: Any = range(steps)
        if progress:
            it = tqdm(it, desc=f"train {name} (SVI)", unit="step", mininterval=0.5)
        loss = float("nan")
        for _ in it:
            loss = svi.step(x, t) / x.shape[0]
            if progress:
                it.set_postfix(elbo_loss=f"{loss:.4f}", refresh=False)
        weights = _guide_weights(guide, shapes, n_samples)
    finally:
        torch.set_num_threads(threads)
    meta = {
        "model": "b-nn",
        "hidden": hidden,
        "steps": steps,
        "batch_size": batch,
        "lr": lr,
        "rank": rank,
        "n_samples": n_samples,
        "seed": seed,
        "final_elbo_loss_per_row": float(loss),
    }
    return BayesianPEM(name=name, norm=norm, weights=weights, metadata=meta)


def _guide_weights(guide: Any, shapes: dict[str, tuple[int, ...]], n_samples: int) -> dict[str, np.ndarray]:
    """``n_samples`` weight sets drawn from the fitted guide, per site ``[n_samples, *shape]`` (float64); the guide
    flattens the sites in the model's sample order, checked against its own unpacking (its median).

    Raises:
        RuntimeError: the guide's latent size or site order differs from the model's."""
    import torch

    offsets = np.cumsum([0, *(math.prod(s) for s in shapes.values())])
    cuts = [slice(int(a), int(b)) for a, b in zip(offsets[:-1], offsets[1:], strict=True)]
    sites = [(k, s, cut) for (k, s), cut in zip(shapes.items(), cuts, strict=True)]
    with torch.no_grad():
        latent = guide.get_posterior().sample((n_samples,)).to(torch.float64)  # [S, D]
        if offsets[-1] != latent.shape[1]:
            raise RuntimeError(f"guide latent has {latent.shape[1]} dims, the sites {offsets[-1]}")
        median = guide.median()
        loc = guide.get_posterior().mean.to(torch.float64)
        for k, _, cut in sites:
            if not torch.allclose(median[k].to(torch.float64).reshape(-1), loc[cut]):
                raise RuntimeError(f"guide site order differs from the model's at {k}")
        return {k: latent[:, cut].reshape(n_samples, *s).numpy() for k, s, cut in sites}
