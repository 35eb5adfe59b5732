"""The cut-in's committor as a chain: the events of one step of the cut-in car (:class:`Grid`), a rollout's continuous
level G (:func:`level`, :func:`continuous_level`) and U_t(G, k), the probability of failure from level G at step t with
the track in regime k (:class:`LevelChain`), which :mod:`pemviz.scenarios.cut_in.tilt` tilts each step's events by.

The zero-variance change of measure draws each step's events x from q(x | s) = p(x | s) Q(s, x) / V(s) (Kollman,
Baggerly, Cox & Picard 1999, Ann. Appl. Probab. 9(2); L'Ecuyer & Tuffin 2008, WSC); here Q is U_{t+1} at the level
and regime an event leads to, an approximation that costs variance only.

Units: metres; levels count steps of late braking (:data:`STEP_M`); probabilities in nats where logged."""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from pemviz.core import exact

GRIDS = {
    "fine": (
        1e-10,
        1e-8,
        1e-7,
        1e-6,
        1e-5,
        1e-4,
        3e-4,
        1e-3,
        1.6e-3,
        2.5e-3,
        4e-3,
        6.3e-3,
        1e-2,
        1.6e-2,
        2.5e-2,
        4e-2,
        6.3e-2,
        0.1,
        0.16,
        0.25,
    ),
    "coarse": (1e-8, 1e-6, 1e-5, 1e-4, 3e-4, 1e-3, 2.5e-3, 6.3e-3, 1.6e-2, 4e-2, 0.1, 0.25),
    "lean": (1e-7, 1e-5, 1e-4, 1e-3, 4e-3, 1.6e-2, 6.3e-2, 0.25),
}
"""Tail masses (ascending) of the bin edges of each measurement error, on either side; the central bin lies between the
last ones. ``lean`` (34 branches) is what the cut-in's tilt uses."""

LN10 = 2.302585092994046
"""log 10 (nats)."""

LMAX = 6
"""The highest level: a continuation this many steps of late braking from failing counts as safe."""

STEP_M = 0.76
"""What one step of late braking costs in closest approach at the moderate setting (the 7.6 m/s closing speed x dt),
metres."""


def level(r: np.ndarray) -> np.ndarray:
    """A continuation's level from its robustness ``r`` (metres, any shape): 0 when it fails, else 1 + floor(r /
    :data:`STEP_M`), capped at :data:`LMAX` (int64, the same shape)."""
    return np.where(r < 0.0, 0, np.minimum(1 + np.floor(np.maximum(r, 0.0) / STEP_M), LMAX)).astype(np.int64)


def continuous_level(lv: np.ndarray, inside_m: np.ndarray, step_m: np.ndarray) -> np.ndarray:
    """The level made continuous, G (float64, the shape of ``lv``): L - 1 + how deep inside the lane the continuation's
    track was when the ACC followed, in lateral steps of the track (capped at 1; 0 where L = 0).

    Args:
        lv: levels (:func:`level`).
        inside_m: the track's margin outside the lane's 2 m band at the follow step (metres, <= 0 inside).
        step_m: the track's lateral speed times dt there (metres)."""
    d = np.maximum(-inside_m, 0.0)
    frac = np.clip(d / np.maximum(step_m, 1e-9), 0.0, 1.0)
    return np.where(lv == 0, 0.0, lv - 1.0 + frac)


def g_bin(g: np.ndarray, width: float, nbins: int) -> np.ndarray:
    """The bin of continuous levels ``g`` (int64, the same shape) among ``nbins`` bins ``width`` wide, the last open."""
    return np.clip((np.asarray(g) / width).astype(np.int64), 0, nbins - 1)


def event_descriptor(u: np.ndarray, p0: np.ndarray) -> np.ndarray:
    """Events of the cut-in car as numbers, float64 [k, 3]: a miss (1 or 0), then each error's signed -log10 tail
    mass (0 at the median), from its uniforms ``u`` [k, 3] (detection, range error, lateral error) and p(detect)
    ``p0`` [k]."""
    miss = u[:, 0] > p0
    out = np.zeros((u.shape[0], 3))
    out[:, 0] = miss
    for c in range(2):
        mass = np.minimum(u[:, 1 + c], 1.0 - u[:, 1 + c])
        out[:, 1 + c] = np.where(miss, 0.0, np.sign(u[:, 1 + c] - 0.5) * -exact.log(np.maximum(mass, 1e-300)) / LN10)
    return out


class Grid:
    """The event classes of one step of the cut-in car: class 0 a miss, 1 + i NB + j a detection with the range error
    in bin i and the lateral error in bin j of :attr:`edges` (in the errors' uniforms); **branches**, the events a
    look-ahead tries: 0 a miss, 1 the central draw, then each error's low and high edges (the other error central).

    Args:
        masses: the tail masses of the edges, ascending, in (0, 0.5) (e.g. ``GRIDS["lean"]``)."""

    def __init__(self, masses: np.ndarray) -> None:
        self.masses = np.asarray(masses, dtype=np.float64)
        g = self.ng = self.masses.size
        self.edges = np.concatenate([[0.0], self.masses, 1.0 - self.masses[::-1], [1.0]])
        self.nb, self.central, self.nbranch = self.edges.size - 1, g, 2 + 4 * g
        self.width = np.diff(self.edges)
        reps = [(1.0, 0.5, 0.5), (0.0, 0.5, 0.5)]
        for c in range(2):
            for tail in (self.masses, 1.0 - self.masses):
                reps += [(0.0, v, 0.5) if c == 0 else (0.0, 0.5, v) for v in tail]
        self.reps = np.array(reps)
        """Each branch's uniforms [NBRANCH, 3]."""
        self.desc = event_descriptor(self.reps, np.full(len(reps), 0.5))
        self.maps = []
        """Per error, [NB, NBRANCH]: a bin's value is the mean of its two edges' branches' values."""
        for c in range(2):
            mp = np.zeros((self.nb, self.nbranch))
            mp[g, 1] = 1.0
            for side in range(2):
                br = 2 + 2 * c * g + side * g + np.arange(g)
                for b in range(g):
                    row = b if side == 0 else self.nb - 1 - b
                    mp[row, br[max(b - 1, 0)]] += 0.5
                    mp[row, br[b]] += 0.5
            self.maps.append(mp)

    def edge(self, mass: float) -> int:
        """The index into :attr:`masses` of the edge nearest tail mass ``mass`` (in log): its low branch is 2 + the
        index, its high branch 2 + NG + the index (range errors; lateral errors 2 NG further)."""
        return int(np.argmin(np.abs(exact.log(self.masses / mass))))

    def p_class(self, p0: np.ndarray) -> np.ndarray:
        """p(class) under the PEMs, float64 [k, 1 + NB^2], for the cut-in car's p(detect) ``p0`` [k]."""
        out = np.empty((p0.size, 1 + self.nb * self.nb))
        out[:, 0] = 1.0 - p0
        out[:, 1:] = p0[:, None] * np.outer(self.width, self.width).reshape(1, -1)
        return out

    def class_values(self, log_qb: np.ndarray) -> np.ndarray:
        """log Q per class [k, 1 + NB^2] (nats) from the branches' log Q [k, NBRANCH]: a bin's Q is the mean of its
        two edges' Q; a joint class (both errors off the centre) takes the larger of its two errors' Q."""
        return exact.log(np.maximum(self._per_class(exact.exp(log_qb)), 1e-300))

    def _per_class(self, q: np.ndarray) -> np.ndarray:
        """Each class's value [k, 1 + NB^2] from the branches' values ``q`` [k, NBRANCH] (linear): the miss's own, a
        bin's the mean of its two edges' (exact: halves), a joint class the larger of its two errors'."""
        qr, ql = q @ self.maps[0].T, q @ self.maps[1].T
        out = np.empty((q.shape[0], 1 + self.nb * self.nb))
        out[:, 0] = q[:, 0]
        out[:, 1:] = np.maximum(qr[:, :, None], ql[:, None, :]).reshape(q.shape[0], -1)
        return out

    def log_value(self, p0: np.ndarray, log_qb: np.ndarray) -> np.ndarray:
        """log V = log sum_c p(c) Q(c) of states whose cut-in car is detected with ``p0`` [k], float64 [k] (nats): the
        classes' Q (from the branches' log Q [k, NBRANCH]) averaged under the PEMs, summed in one order (the same on
        every CPU)."""
        v = np.cumsum(self.p_class(p0) * exact.exp(self.class_values(log_qb)), axis=1)[:, -1]
        return exact.log(np.clip(v, 1e-300, 1.0))

    def proposal(self, p0: np.ndarray, log_qb: np.ndarray, eps: float) -> tuple[np.ndarray, np.ndarray]:
        """(p(class), q(class)), float64 [k, 1 + NB^2] each: the tilt p Q normalised (Q from the branches' log Q
        [k, NBRANCH]), mixed with a share ``eps`` of p itself (a defensive mixture: Hesterberg 1995, Technometrics
        37(2)), so that every weight p / q is at most 1 / eps."""
        pc = self.p_class(p0)
        t = self._per_class(exact.exp(log_qb - np.max(log_qb, axis=1, keepdims=True)))  # Q over its largest's
        t *= pc
        total = np.cumsum(t, axis=1)[:, -1:]  # summed in one order (a vector reduction's would depend on the CPU)
        return pc, (1.0 - eps) * (t / total) + eps * pc

    def classify(self, u: np.ndarray, p0: np.ndarray) -> np.ndarray:
        """The class (int64 [k]) of the uniforms ``u`` [k, 3] given p(detect) ``p0`` [k]."""
        bi, bj = (np.clip(np.searchsorted(self.edges, u[:, c], side="right") - 1, 0, self.nb - 1) for c in (1, 2))
        return np.where(u[:, 0] > p0, 0, 1 + bi * self.nb + bj)

    def draw(self, cls: np.ndarray, p0: np.ndarray, x: np.ndarray) -> np.ndarray:
        """Uniforms [k, 3] uniform inside each class ``cls`` [k] (density 1 / p(class) there, under the PEMs' uniform
        density), from fresh uniforms ``x`` [k, 3]."""
        miss = cls == 0
        i, j = np.divmod(np.maximum(cls - 1, 0), self.nb)
        e = self.edges
        ud = np.where(miss, p0 + x[:, 0] * (1.0 - p0), x[:, 0] * p0)
        ur = np.where(miss, x[:, 1], e[i] + x[:, 1] * (e[i + 1] - e[i]))
        ul = np.where(miss, x[:, 2], e[j] + x[:, 2] * (e[j + 1] - e[j]))
        return np.column_stack([ud, ur, ul])


class LevelChain:
    """U_t(g, k): the probability of failure from continuous level g (:func:`continuous_level`) at step t, the track in
    regime k, solved backwards from 1[g <= 0] at the window's end on a grid of g (step ``h``):

        U_t(g, k) = sum_c p_t(c) U_{t+1}(g + delta_{k,b}(c), k'_{k,b}(c)),

    each class c shifting g by its effect on the representative state of the cell (regime k, bin b of g) nearest to
    it, the range and lateral errors' effects added, and moving it to the regime its branch ends in (a joint class:
    its range error's). A cell without a representative takes its regime's nearest bin's, a regime without any the
    nominal path's (the first cell of ``effects[t]``); a step without effects leaves g and k as they are.

    Args:
        grid: the events.
        window: (first, end) steps tilted.
        p0s: step -> the cut-in car's p(detect) on the nominal path.
        effects, nexts: step -> cell (k x nbins + bin) -> its branches' shifts of G [NBRANCH] and next regimes.
        nreg: the regimes.
        h, gmax: the grid of g (levels).
        g_nom: step -> the nominal path's G (for reports).
        states: step -> the representatives looked ahead (for reports).
        bin_width: the width of a cell's bin of g (None: one bin)."""

    def __init__(
        self,
        grid: Grid,
        window: tuple[int, int],
        p0s: Mapping[int, float],
        effects: Mapping[int, dict],
        nexts: Mapping[int, dict],
        nreg: int,
        h: float,
        gmax: float,
        g_nom: Mapping[int, float] | None = None,
        states: Mapping[int, int] | None = None,
        bin_width: float | None = None,
    ) -> None:
        self.g = np.arange(0.0, gmax + h, h)
        self.window, self.nbranch = window, grid.nbranch
        self.g_nom, self.states = dict(g_nom or {}), dict(states or {})
        self.bin_width = bin_width or 2.0 * (gmax + h)
        self.nbins = int(np.ceil((gmax + h) / self.bin_width))
        bins = self.bin_of(self.g)
        w0, w1 = window
        outer = np.array([np.flatnonzero(grid.maps[0][row])[0] for row in range(grid.nb)])  # each range bin's branch
        u = np.tile((self.g <= 1e-9).astype(float), (nreg, 1))
        self.log_table = {w1: exact.log(np.maximum(u, 1e-300))}
        self.effects: dict[int, np.ndarray] = {}  # per step: each cell's shifts of G [nreg, nbins, NBRANCH]
        self.nexts: dict[int, np.ndarray] = {}  # and next regimes
        for t in range(w1 - 1, w0 - 1, -1):
            if t in effects:
                new = np.zeros_like(u)
                pc = grid.p_class(np.array([p0s[t]]))[0]
                keys = self.nearest_cells(list(effects[t]), nreg)
                self.effects[t] = np.array([[effects[t][c] for c in row] for row in keys])
                self.nexts[t] = np.array([[nexts[t][c] for c in row] for row in keys])
                for k in range(nreg):
                    for cell in np.unique(keys[k]):
                        gsel = np.flatnonzero(keys[k][bins] == cell)
                        e, nxt = effects[t][cell], nexts[t][cell]
                        dr, dl = (mp @ e / np.maximum(mp.sum(axis=1), 1e-12) for mp in grid.maps)
                        delta = np.concatenate([[e[0]], (dr[:, None] + dl[None, :]).ravel()])
                        cls_reg = np.concatenate(
                            [
                                [nxt[0]],
                                np.repeat(np.where(np.arange(grid.nb) == grid.central, nxt[1], nxt[outer]), grid.nb),
                            ]
                        )
                        for k2 in np.unique(cls_reg):
                            sel = np.flatnonzero(cls_reg == k2)
                            shifted = np.interp(
                                self.g[None, gsel] + delta[sel, None], self.g, u[k2], left=1.0, right=u[k2, -1]
                            )
                            new[k, gsel] += pc[sel] @ shifted
                u = new
            self.log_table[t] = exact.log(np.maximum(u, 1e-300))

    def bin_of(self, g: np.ndarray) -> np.ndarray:
        """The bin of continuous levels ``g`` (int64, the same shape)."""
        return g_bin(g, self.bin_width, self.nbins)

    def nearest_cells(self, cells: list, nreg: int) -> np.ndarray:
        """For every regime and bin, the cell of ``cells`` (k x nbins + bin; the first is the nominal path's) whose
        effects it takes, int64 [nreg, nbins]: its own, else its regime's nearest bin, else the nominal regime's
        nearest."""
        have = np.array(cells)
        out = np.empty((nreg, self.nbins), dtype=np.int64)
        bins = np.arange(self.nbins)
        for k in range(nreg):
            own = have[have // self.nbins == k]
            pool = own if own.size else have[have // self.nbins == have[0] // self.nbins]
            out[k] = pool[np.argmin(np.abs(pool[None, :] % self.nbins - bins[:, None]), axis=1)]
        return out

    def log_q_branches(
        self, t: int, g0: np.ndarray, regime: np.ndarray, shifts: np.ndarray | None = None
    ) -> np.ndarray:
        """log U_{t+1} after each branch, float64 [k, NBRANCH] (nats), of states at step t whose continuous level is
        ``g0`` [k] and regime ``regime`` (int [k]): every branch's shift of G (``shifts`` [k, NBRANCH] where given,
        else the cell's representative's) and next regime (the representative's) read from the chain, no look-ahead;
        a step without effects leaves both as they are."""
        if t not in self.effects:
            return np.repeat(self.log_u(t + 1, g0, regime)[:, None], self.nbranch, axis=1)
        b = self.bin_of(g0)
        gl = g0[:, None] + (self.effects[t][regime, b] if shifts is None else shifts)
        return self.log_u(t + 1, gl, self.nexts[t][regime, b])

    def log_u(self, t: int, gl: np.ndarray, regime: np.ndarray | None = None) -> np.ndarray:
        """log U_t (nats) at continuous levels ``gl`` (any shape), in regimes ``regime`` (int, the same shape; None:
        0); steps outside the window take its nearest end."""
        table = self.log_table[min(max(t, self.window[0]), self.window[1])]
        if regime is None:
            return np.interp(gl, self.g, table[0])
        out = np.empty(np.shape(gl))
        for k in np.unique(regime):
            out[regime == k] = np.interp(gl[regime == k], self.g, table[k])
        return out
