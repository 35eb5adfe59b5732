"""Adaptive importance sampling of detector outputs (Innes & Ramamoorthy 2022, Algorithm 1): the proposal networks
q_phi(detect | h(s)) and their cross-entropy fits to each stage's elites (robustness at or below gamma_kappa),
importance weights raised to the smoothing power alpha."""

from __future__ import annotations

import math
import os
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from pemviz.core import exact, torch_use
from pemviz.core.detectors import GAP_COLUMN
from pemviz.core.exact_fit import fit_exact
from pemviz.core.files import atomic_write, load_tagged
from pemviz.core.fit_settings import CHECK_EVERY, EXACT, PLATEAU_EPOCHS, Objective
from pemviz.methods.adaptive import FITS

if TYPE_CHECKING:
    import torch

    from pemviz.core.torch_fits import ProposalModule


def torch_imported() -> bool:
    """Whether a new :class:`Proposal` starts in torch: whether torch is imported already
    (:func:`pemviz.core.torch_use.imported`)."""
    return torch_use.imported()


GAP_SCALE_M = 12.0
"""The default input scale of a proposal: its input is the first observation column / 12 (e.g. the braking
scenario's gap / 12 m: Innes & Ramamoorthy 2022, the authors' code)."""


class Proposal:
    """q_phi(a | d): Linear(1,32)-ReLU-Linear(32,32)-ReLU-Linear(32,2)-LogSoftmax, float64 (Innes & Ramamoorthy 2022,
    Algorithm 1; the authors' ``FFPolicy``).

    ``forward(values [M]) -> [M, 2]`` log-probabilities (nats) of (miss, detect); the network sees ``h(s) = values /
    h_scale``. Its parameters live in numpy (float64, torch's layout) until something needs them in torch
    (:attr:`net`), then move for good into a :class:`pemviz.core.torch_fits.ProposalModule`; sampling
    (:meth:`detect_logit`), the exact fits and :meth:`curve` read either, so a run whose fits are exact never
    imports torch."""

    def __init__(self, h_scale: float = GAP_SCALE_M) -> None:
        self.h_scale = float(h_scale)
        self._arrays: list[np.ndarray] | None = None
        """The parameters while they live in numpy (None: not drawn yet, or moved into :attr:`_module`)."""
        self._version = 0
        """Bumped by every change of :attr:`_arrays` (the sampling weights' cache follows it)."""
        self._module: ProposalModule | None = None
        """The torch module (:class:`pemviz.core.torch_fits.ProposalModule`) once the parameters moved there."""
        self._training = True
        if torch_imported():
            self._to_torch()

    @property
    def n_inputs(self) -> int:
        """k, the network's inputs: 1 (the gap)."""
        return 1

    @property
    def net(self):
        """The torch network (``nn.Sequential``, float64); the parameters move into torch for good (imports torch)."""
        return self._to_torch().net

    @property
    def noise_shift(self):
        """The measurement-error head (:class:`pemviz.core.torch_fits.NoiseShift`, :meth:`add_noise_head`; None: the
        errors are drawn from the target's model)."""
        return None if self._module is None else self._module.noise_shift

    def _to_torch(self):
        """The torch module holding the parameters, made (and the numpy parameters copied in) the first time."""
        if self._module is None:
            from pemviz.core.torch_fits import ProposalModule, new_net
            from pemviz.core.torch_use import torch_module

            torch = torch_module()
            if self._arrays is None:
                module = ProposalModule(new_net(self.n_inputs))
            else:
                with torch.random.fork_rng(devices=[]):  # its own weights: torch's random state left as it was
                    module = ProposalModule(new_net(self.n_inputs))
                with torch.no_grad():
                    for p, a in zip(module.net.parameters(), self._arrays, strict=False):
                        p.copy_(torch.from_numpy(a))
            module.train(self._training)
            self._module, self._arrays = module, None
        return self._module

    def layer_shapes(self) -> list[tuple[int, ...]]:
        """The parameters' shapes in ``net.parameters()`` order: W1 [32, k], b1 [32], W2 [32, 32], b2, W3 [2, 32],
        b3."""
        return [(32, self.n_inputs), (32,), (32, 32), (32,), (2, 32), (2,)]

    def parameter_arrays(self) -> list[np.ndarray]:
        """The network's parameters, float64, in :meth:`layer_shapes` order (read-only views while in numpy; copies
        of torch's)."""
        module = self._module
        if module is None:
            if self._arrays is None:
                module = self._to_torch()  # never initialised: torch's default initialisation, as before
            else:
                views = [a.view() for a in self._arrays]
                for v in views:
                    v.flags.writeable = False
                return views
        return [p.detach().numpy().copy() for p in module.net.parameters()]

    def set_parameter_arrays(self, arrays: list[np.ndarray]) -> None:
        """Replace the network's parameters by ``arrays`` (float64, :meth:`layer_shapes` order; copied).

        Raises:
            ValueError: a shape differs from :meth:`layer_shapes`."""
        arrays = [np.array(a, dtype=np.float64, copy=True) for a in arrays]
        if [a.shape for a in arrays] != self.layer_shapes():
            shapes = [a.shape for a in arrays]
            raise ValueError(f"proposal parameters of shapes {shapes}, expected {self.layer_shapes()}")
        if self._module is None:
            self._arrays = arrays
            self._version += 1
            return
        from pemviz.core.torch_use import torch_module

        torch = torch_module()
        with torch.no_grad():
            for p, a in zip(self._module.net.parameters(), arrays, strict=False):
                p.copy_(torch.from_numpy(a))

    def forward(self, values):
        """log q [M, 2] (nats, torch float64) at proposal inputs ``values`` [M] (a torch tensor; imports torch)."""
        return self.net(self.inputs(values))

    __call__ = forward

    def initialise(self, rng: np.random.Generator) -> None:
        """Draw every layer's weights and biases i.i.d. U(-1/sqrt(fan_in), 1/sqrt(fan_in)), as torch's ``nn.Linear``
        initialises them (He et al., "Delving deep into rectifiers", 2015, with a = sqrt(5)), from ``rng`` (numpy's
        PCG64: the same numbers on every CPU, where torch's ``uniform_`` rounds by the CPU's vector unit): each layer's
        weight [out, in], then its bias, layer by layer."""
        shapes = self.layer_shapes()
        bounds = [1.0 / math.sqrt(shapes[i - i % 2][1]) for i in range(len(shapes))]  # the layer's fan-in
        self.set_parameter_arrays([rng.uniform(-b, b, shape) for b, shape in zip(bounds, shapes, strict=False)])

    def add_noise_head(self, n_noise: int) -> None:
        """Give the proposal a measurement-error model of its own (:class:`pemviz.core.torch_fits.NoiseShift`, equal
        to the target's until fitted) for the D = ``n_noise`` error components a noisy target draws (imports torch)."""
        from pemviz.core.torch_fits import NoiseShift

        self._to_torch().noise_shift = NoiseShift(self.n_inputs, n_noise)

    def noise_shift_of(self, obs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(a [N, D], b [N, D]) of the error head at observations (object rows) [N, F]
        (:class:`pemviz.core.torch_fits.NoiseShift`)."""
        from pemviz.core.torch_use import torch_module

        torch = torch_module()
        x = np.asarray(obs, dtype=np.float64)[:, self.input_columns()] / self.input_scales()
        with torch.no_grad():
            a, b = self.noise_shift(torch.from_numpy(np.ascontiguousarray(x)))
        return a.numpy(), b.numpy()

    def inputs(self, values):
        """The network's input h(s) of proposal inputs ``values`` [M] (the first observation column's unit, a torch
        tensor): [M, 1], dimensionless."""
        return (values / self.h_scale).reshape(-1, 1)

    def input_array(self, values: np.ndarray) -> np.ndarray:
        """:meth:`inputs` in numpy: float64 [M, k] of proposal inputs ``values`` [M] or [M, k] (the same bits)."""
        return np.asarray(values, dtype=np.float64).reshape(-1, self.n_inputs) / self.input_scales()

    def detect_logit(self, obs: np.ndarray) -> np.ndarray:
        """Detector interface: logit q(detect | obs) = log q(detect) - log q(miss), float64 [N] for observations [N, F]
        (nats).

        The network of :meth:`forward` in exact, order-free arithmetic (:mod:`pemviz.core.exact`): within ~1e-6 of
        ``forward``'s, and the same bits for a row whatever rows come with it, whatever the CPU. Sampling and every
        importance weight use this logit."""
        logits, inverse = self._network_distinct(obs)
        return logits if inverse is None else logits[inverse]

    @property
    def logit_by_row(self) -> bool:
        """Whether :meth:`detect_logit` of a row is a function of its bits alone, whatever rows are asked with it (the
        exact network's, not a subclass's own): :class:`pemviz.core.detectors.StageSamplers` then keeps the logits
        of rows unchanged since the last step."""
        return type(self).detect_logit is Proposal.detect_logit

    def distinct_logit(self, obs: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        """:meth:`detect_logit` of each distinct row of observations [N, F] once (by their bits; from
        :data:`DISTINCT_FROM` rows, where at most 3/4 of them are distinct): (the logits float64 [U], each row's index
        into them int [N]), or (the logits [N], None), as also for a subclass with a :meth:`detect_logit` of its own."""
        if type(self).detect_logit is not Proposal.detect_logit:
            return np.asarray(self.detect_logit(obs), dtype=np.float64), None
        return self._network_distinct(obs)

    def _network_distinct(self, obs: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        """The network's logits of :meth:`distinct_logit`."""
        obs = np.asarray(obs, dtype=np.float64)
        columns = self.input_columns()
        x = obs if columns == list(range(obs.shape[1])) else obs[:, columns]
        weights = self._sampling_weights()
        if x.shape[0] == 0:
            return np.zeros(0), None
        if x.shape[0] >= DISTINCT_FROM:  # rollouts of the same past share their rows
            x = np.ascontiguousarray(x)
            distinct = _distinct_rows(x)
            if distinct is not None:
                return _network_logit(x[distinct[0]], weights), distinct[1]
        return _network_logit(x, weights), None

    def __getstate__(self) -> dict:
        """Pickled and copied without the sampling weights' cache (it holds storages; a copy computes its own)."""
        return {k: v for k, v in self.__dict__.items() if k != "_sampling_cache"}

    def _parameter_key(self) -> tuple:
        """What identifies the parameters' current values: the numpy version, or each torch parameter's storage and
        version (a fit swaps storages in, ``p.data = ...``; optimisers and ``load_state_dict`` bump versions; the
        storages seen are held by the cache, so no new one can take an old one's address). An update through
        ``p.data`` in place leaves no trace: change parameters under ``torch.no_grad()`` instead."""
        if self._module is None:
            return ("numpy", self._version, id(self._arrays))
        return ("torch", *((p.data_ptr(), p._version) for p in self._module.net.parameters()))

    def _sampling_weights(self) -> tuple:
        """The weights of :meth:`detect_logit`, each layer's on its grid (:func:`pemviz.core.exact.on_grid`, per
        output unit) with its values (:func:`pemviz.core.exact.scaled_grid`; None for a layer with a bias of exactly
        0): (W1 [k, 32] with the input scales folded in, W2 [32, 32], w_detect - w_miss [32, 1], then the biases
        b1 [32, 1], b2 [32, 1], b_detect - b_miss), kept while the parameters and input scales are unchanged
        (:meth:`_parameter_key`)."""
        if self._module is None and self._arrays is None:
            self._to_torch()  # never initialised: torch's default initialisation, as before
        cached = self.__dict__.get("_sampling_cache")
        key = (tuple(self.input_scales().tolist()), self._parameter_key())
        if cached is not None and cached[0] == key:
            return cached[1]
        w1, b1, w2, b2, w, b = self.parameter_arrays()
        w1 = w1.T / self.input_scales()[:, None]
        w2 = w2.T
        w3 = (w[1] - w[0])[:, None]
        b1, b2, b3 = b1.copy(), b2.copy(), float(b[1] - b[0])
        grids = [exact.on_grid(w, exact.grid_bits(w.shape[0]), 0) for w in (w1, w2, w3)]
        # a bias of exactly 0 would let matmul_t's sign of a zero through: that layer's products as exact.matmul's
        biases = (b1, b2, b3)
        scaled = [None if np.any(bias == 0.0) else exact.scaled_grid(g) for g, bias in zip(grids, biases, strict=True)]
        weights = tuple(zip(grids, scaled, strict=True)) + (b1[:, None], b2[:, None], b3)
        held = () if self._module is None else tuple(p.untyped_storage() for p in self._module.net.parameters())
        self.__dict__["_sampling_cache"] = (key, weights, held)
        return weights

    def input_columns(self) -> list[int]:
        """The observation columns the network reads, in its input order: the gap."""
        return [GAP_COLUMN]

    def input_scales(self) -> np.ndarray:
        """What :meth:`inputs` divides each input column by, float64 [k]: the gap's ``h_scale`` (metres)."""
        return np.array([self.h_scale], dtype=np.float64)

    def _curve_inputs(self, gap_grid_m: np.ndarray) -> np.ndarray:
        """The proposal inputs [G, k] of :meth:`curve`: the gaps."""
        return np.asarray(gap_grid_m, dtype=np.float64).reshape(-1)

    def curve(self, gap_grid_m: np.ndarray) -> np.ndarray:
        """q(detect | d) on a grid of gaps (metres), float64 [G]: the network in numpy float64 (a ReLU network's
        forward pass, the log-softmax of its two outputs as ``-softplus(z_miss - z_detect)``)."""
        w1, b1, w2, b2, w3, b3 = self.parameter_arrays()
        h = self.input_array(self._curve_inputs(gap_grid_m))
        a = np.maximum(h @ w1.T + b1, 0.0)
        a = np.maximum(a @ w2.T + b2, 0.0)
        z = a @ w3.T + b3
        return np.exp(-np.logaddexp(0.0, z[:, 0] - z[:, 1]))

    def features(self, observations: np.ndarray) -> np.ndarray:
        """The proposal's inputs of rollouts' observations [N, T, F]: the gap, [N, T] (metres)."""
        return np.asarray(observations)[..., GAP_COLUMN]

    # -- torch's module interface, where callers use it ---------------------------------------------------------
    def state_dict(self) -> dict:
        """The torch ``state_dict`` (``net.0.weight`` ...; imports torch)."""
        return self._to_torch().state_dict()

    def load_state_dict(self, state: dict) -> None:
        """Load a ``state_dict`` of torch tensors or numpy arrays: into numpy while the parameters live there and it
        holds the network alone, else into torch (imports torch).

        Raises:
            ValueError: a numpy load of the wrong shapes; RuntimeError: torch's, for wrong keys or shapes."""
        keys = [f"net.{i}.{k}" for i in range(0, 6, 2) for k in ("weight", "bias")]  # the three Linear layers
        if self._module is None and set(state) == set(keys):
            self.set_parameter_arrays([np.asarray(state[k], dtype=np.float64) for k in keys])
            return
        from pemviz.core.torch_use import torch_module

        torch = torch_module()
        self._to_torch().load_state_dict({k: torch.as_tensor(v) for k, v in state.items()})

    def parameters(self):
        """The torch parameters (imports torch)."""
        return self._to_torch().parameters()

    @property
    def training(self) -> bool:
        """Whether the proposal is in training mode (torch's flag; a checkpoint loads in eval mode)."""
        return self._training

    def train(self, mode: bool = True) -> Proposal:
        self._training = bool(mode)
        if self._module is not None:
            self._module.train(mode)
        return self

    def eval(self) -> Proposal:
        return self.train(False)


DISTINCT_FROM = 256
"""Rows from which :meth:`Proposal.detect_logit` evaluates the network once per distinct row of inputs (by their bits:
a row's logit is a function of its own bits alone), where at most 3/4 of them are distinct: rollouts that drew the same
detections so far share their state (e.g. about half the rows of a braking stage)."""


_MIX = np.uint64(0x9E3779B97F4A7C15)
"""An odd 64-bit multiplier (2^64 / golden ratio): it mixes a row's columns into one key (:func:`_distinct_rows`)."""


def _distinct_rows(x: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """(one row of each distinct row of ``x`` float64 [n, k] by its bits, int [m]; the distinct row of each row, int
    [n]) where at most 3/4 of the rows are distinct, else None; rows are keyed by a uint64 hash of their bits
    (Fibonacci hashing, :data:`_MIX`) and placed in a table of at least 8 n slots by successive fields of their keys'
    bits (no sort: a row whose slot holds another key tries the next field), and a key shared by two different rows
    (or a row left without a slot after four fields) also gives None."""
    bits = x.view(np.uint64)
    key = bits[:, 0].copy()
    for j in range(1, bits.shape[1]):
        key *= _MIX
        key ^= bits[:, j]
    key *= _MIX
    n = key.size
    width = max(10, (n - 1).bit_length() + 3)  # the table's bits: at least 8 n slots
    table = np.empty(1 << width, np.intp)
    rep = np.empty(n, np.intp)  # each row's representative
    todo, keys = np.arange(n), key
    for field in range(64 // width):  # the highest bits first, then the next field of as many
        slot = ((keys >> np.uint64(64 - width * (field + 1))) & np.uint64((1 << width) - 1)).astype(np.intp)
        table[slot] = todo  # one row per slot: any of its rows
        held = table[slot]
        placed = key[held] == keys
        rep[todo[placed]] = held[placed]
        todo = todo[~placed]
        if not todo.size:
            break
        keys = key[todo]
    if todo.size:
        return None
    distinct = np.zeros(n, bool)
    distinct[rep] = True
    first = np.flatnonzero(distinct)
    if 4 * first.size > 3 * n:
        return None
    columns = np.ascontiguousarray(bits.T)  # [k, n]: a row's representative compared column by column
    if not all(np.array_equal(c[rep], c) for c in columns):  # a key shared by different rows
        return None
    return first, (np.cumsum(distinct) - 1)[rep]


NETWORK_BLOCK = 1024
"""Rows :func:`_network_logit` evaluates together: the activations [32, 1024] (256 KB) stay in a core's cache (twice
as fast a row as 8,192 together on the 2-core CI machine); a row's logit is its own whatever the block."""


def _network_logit(x: np.ndarray, weights: tuple) -> np.ndarray:
    """The logit of :meth:`Proposal.detect_logit`, float64 [N], of inputs x [N, k] and the weights of
    :meth:`Proposal._sampling_weights`: three products on grids, each row's from its own inputs alone, computed on the
    transposed activations [32, N] (:func:`pemviz.core.exact.matmul_t`, the bits of
    :func:`pemviz.core.exact.matmul`), :data:`NETWORK_BLOCK` rows at a time."""
    (g1, t1), (g2, t2), (g3, t3), b1, b2, b3 = weights
    out = np.empty(x.shape[0])
    for lo in range(0, x.shape[0], NETWORK_BLOCK):
        a = exact.matmul_t(x[lo : lo + NETWORK_BLOCK].T.copy(), g1, t1, own=True)  # a copy of its own, C-contiguous
        a += b1
        np.maximum(a, 0.0, out=a)
        a = exact.matmul_t(a, g2, t2, nonneg=True, own=True)
        a += b2
        np.maximum(a, 0.0, out=a)
        np.add(exact.matmul_t(a, g3, t3, nonneg=True, own=True)[0], b3, out=out[lo : lo + NETWORK_BLOCK])
    return out


class StateProposal(Proposal):
    """q_phi(a | h(s)) with h(s) = several observation columns, each divided by its scale (pemviz's default sampler).

    Same network as :class:`Proposal` with ``len(columns)`` inputs (gap first). ``forward(h [M, k])``;
    :meth:`curve` varies the gap and holds the other inputs at ``reference`` (e.g. the start state).
    Opt in with ``ExperimentConfig.proposal_inputs = "state"``; the paper's proposal sees the gap only."""

    def __init__(self, columns: tuple[int, ...], scales: tuple[float, ...], reference: tuple[float, ...]) -> None:
        if len(columns) != len(scales) or len(columns) != len(reference) or columns[:1] != (GAP_COLUMN,):
            raise ValueError("StateProposal: columns, scales and reference need one entry per input, the gap first")
        self.columns, self.reference = tuple(columns), tuple(float(r) for r in reference)
        self.scales = np.asarray(scales, dtype=np.float64)
        super().__init__(float(scales[0]))

    @property
    def n_inputs(self) -> int:
        """k, the network's inputs: one per column."""
        return len(self.columns)

    def inputs(self, h):
        """The network's input of proposal inputs ``h`` [M, k] (observation units, a torch tensor): [M, k], each
        column divided by its scale."""
        from pemviz.core.torch_use import torch_module

        return h.reshape(-1, len(self.columns)) / torch_module().as_tensor(self.scales)

    def features(self, observations: np.ndarray) -> np.ndarray:
        """[N, T, k]: the proposal's input columns of observations [N, T, F] (the observations themselves, not a copy,
        when the columns are all of them in order)."""
        observations = np.asarray(observations)
        if self.columns == tuple(range(observations.shape[-1])):
            return observations
        return observations[..., list(self.columns)]

    def input_columns(self) -> list[int]:
        """The observation columns the network reads, in its input order (the gap first)."""
        return list(self.columns)

    def input_scales(self) -> np.ndarray:
        """Each input column's scale, float64 [k] (observation units)."""
        return self.scales

    def _curve_inputs(self, gap_grid_m: np.ndarray) -> np.ndarray:
        """[G, k]: the gaps, the other inputs held at ``reference``."""
        h = np.tile(np.asarray(self.reference, dtype=np.float64), (np.size(gap_grid_m), 1))
        h[:, 0] = gap_grid_m
        return h


class FeatureProposal(StateProposal):
    """A :class:`StateProposal` over the object rows with the step's state features appended
    (:mod:`pemviz.core.features`): it reads them (``reads_state``), so :func:`pemviz.core.lockstep.run_batched` asks
    it about each row with its object's and its ego's features after the row's own columns."""

    reads_state = True


def fit_proposal(
    proposal: Proposal,
    inputs: np.ndarray | torch.Tensor,
    objective: Objective,
    epochs: int,
    lr: float,
    check: Callable[[], None] | None = None,
    optimizer: str = "adam",
    tolerance: float | None = None,
    per: float | None = None,
    dtype: Any = EXACT,
) -> list[float]:
    """Minimise the ``objective`` of log q_phi(. | ``inputs``) over the proposal's parameters, in place; returns the
    loss per step. ``adam`` (Kingma & Ba 2015) backpropagates by hand (:func:`pemviz.core.exact_fit.fit_exact`,
    :class:`pemviz.core.torch_fits.Backprop`); ``lbfgs`` (Nocedal 1980; torch's, strong-Wolfe) uses autograd.

    Args:
        proposal: the :class:`Proposal` fitted, in place.
        inputs: the proposal's inputs, float64 [M] (gaps, metres) or [M, k] (:meth:`Proposal.forward`).
        objective: see :data:`pemviz.core.fit_settings.Objective`.
        per: with a tensor C, the loss is ``-sum(C * log q) / per``; None: not divided.
        epochs: Adam steps, or the most L-BFGS iterations.
        lr: the step size.
        check: called every :data:`pemviz.core.fit_settings.CHECK_EVERY` steps; may raise to abandon the fit.
        dtype: an ``adam`` fit's arithmetic: :data:`pemviz.core.fit_settings.EXACT` (default, the same on every CPU)
            or torch's ``"float32"`` / ``"float64"``; weights stay exact float64 either way.
        optimizer: one of :data:`pemviz.methods.adaptive.FITS`.
        tolerance: ``adam``: stop once the loss fell by less than this over
            :data:`pemviz.core.fit_settings.PLATEAU_EPOCHS` epochs (None: every epoch); ``lbfgs``: its tolerance
            (default :data:`pemviz.core.fit_settings.LBFGS_TOLERANCE`).
    Returns:
        the loss per Adam epoch, or per L-BFGS evaluation; ``[]`` for no ``inputs`` (M = 0).
    Raises:
        ValueError: for an unknown ``optimizer``."""
    if optimizer not in FITS:
        raise ValueError(f"fit_proposal: unknown optimizer {optimizer!r}; use one of {', '.join(FITS)}")
    own_fit = getattr(proposal, "fit_counts", None)
    if own_fit is not None and not callable(objective):  # a proposal with a fit of its own (a GLM's)
        counts = objective if isinstance(objective, np.ndarray) else objective.detach().numpy()
        return own_fit(np.asarray(inputs, dtype=np.float64), np.asarray(counts, dtype=np.float64), check)
    if len(inputs) == 0:  # no step to fit (every rollout failed before its first action): the proposal as it is
        return []
    if optimizer == "adam" and dtype == EXACT and not callable(objective):
        counts = objective if isinstance(objective, np.ndarray) else objective.detach().numpy()
        return fit_exact(
            proposal,
            np.asarray(inputs, dtype=np.float64),
            counts,
            epochs,
            lr,
            check,
            tolerance,
            per,
            check_every=CHECK_EVERY,
            plateau_epochs=PLATEAU_EPOCHS,
        )
    from pemviz.core.torch_fits import fit_in_torch

    return fit_in_torch(proposal, inputs, objective, epochs, lr, check, optimizer, tolerance, per, dtype)


# ---------------------------------------------------------------------------------- proposal checkpoints

PROPOSAL_FORMAT_TAG = "pemviz-proposal"
PROPOSAL_FORMAT_VERSION = 1
SAMPLE_PRECISIONS = ("exact", "float64", "float32")
"""A checkpoint's ``sample_precision``: ``exact`` (written now); ``float64`` and ``float32`` (written before sampling
became exact, read and sampled exactly)."""


class ProposalFormatError(ValueError):
    """A file is not a readable pemviz proposal checkpoint: the message names the file and why."""


def write_proposal_file(proposal: Proposal, path: str | os.PathLike[str]) -> None:
    """``torch.save`` a :class:`Proposal` checkpoint into ``path`` as it is (no temporary file; else
    :func:`save_proposal`): a plain dict of format tag, version, ``h_scale`` (metres), a copy of the ``state_dict``
    and ``sample_precision``, readable with ``torch.load(weights_only=True)``."""
    payload = {
        "format": PROPOSAL_FORMAT_TAG,
        "version": PROPOSAL_FORMAT_VERSION,
        "h_scale": float(proposal.h_scale),
        "state_dict": {k: v.detach().cpu().clone() for k, v in proposal.state_dict().items()},
        "sample_precision": "exact",
    }
    from pemviz.core.torch_use import torch_module

    torch_module().save(payload, path)


def save_proposal(proposal: Proposal, path: str | os.PathLike[str], *, overwrite: bool = True) -> Path:
    """Write a :class:`Proposal` checkpoint (:func:`write_proposal_file`) atomically; returns ``path``.

    Raises:
        OSError: the folder is missing or not writable, the disk is full (nothing is left behind).
        pemviz.core.files.OutputExists: ``path`` exists and ``overwrite`` is False."""
    return atomic_write(path, lambda tmp: write_proposal_file(proposal, tmp), overwrite=overwrite)


def load_proposal(path: str | os.PathLike[str]) -> Proposal:
    """Load a proposal saved by :func:`save_proposal`, in eval mode.

    Raises:
        FileNotFoundError: no such file.
        ProposalFormatError: not a pemviz proposal checkpoint, another format version, or damaged weights."""
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"proposal checkpoint {p} not found")
    payload = load_tagged(
        p, PROPOSAL_FORMAT_TAG, PROPOSAL_FORMAT_VERSION, "proposal checkpoint", ProposalFormatError, as_numpy=True
    )
    try:
        proposal = Proposal(float(payload["h_scale"]))
        proposal.load_state_dict(payload["state_dict"])
        precision = payload.get("sample_precision", "float64")
        if precision not in SAMPLE_PRECISIONS:
            raise ValueError(f"sample_precision {precision!r} is none of {', '.join(SAMPLE_PRECISIONS)}")
    except (KeyError, TypeError, ValueError, RuntimeError) as exc:
        raise ProposalFormatError(f"{p}: damaged proposal checkpoint ({exc})") from None
    return proposal.eval()
