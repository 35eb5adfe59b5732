"""How long a new track's velocity estimate takes to come within 2 m/s of the truth, under a velocity prior (the
guide's *A realistic perception stack*, docs/realistic-stack.md: its advice on ``prior_vx_mps``).

The ego drives at 20 m/s towards a car first seen 50 m ahead (a cut-out's reveal); the car is stopped (0 m/s) or
drives at the ego's speed (20 m/s). Every 0.1 s step, for 2 s, the camera sees it
(``pemviz.stack.camera.view``), the shipped PEMs detect it and mislocate it (``pemviz.stack.detector.perceive``: the
detection PEM and the noise PEM's heavy-tailed errors), and the library's tracker (``pemviz.stack.tracker``, default
``TrackerParams`` but the velocity prior's std) folds the measurements in. Prints, per prior and true speed, the
time from which the median (and the 90th percentile) over the rollouts of the track's velocity error stays within
2 m/s (inf: not within the 2 s), and the median estimate at 0.5 s and 1.0 s.

Usage: python benchmarks/track_prior.py [--n 2000] [--seed 0]    (about 50 s on one core)
"""

from __future__ import annotations

import argparse

import numpy as np
from pemviz.stack import camera, tracker
from pemviz.stack.detector import VISIBLE, camera_detector, perceive

DT, STEPS, EGO_MPS, FIRST_RANGE_M, TOLERANCE_MPS = 0.1, 20, 20.0, 50.0, 2.0
NAMES = (*camera.SALIENT_NAMES, VISIBLE)
PRIORS = {
    "ego's speed, std 5 m/s": (EGO_MPS, 5.0),
    "ego's speed, std 15 m/s": (EGO_MPS, 15.0),
    "half the ego's speed, std 5.8 m/s": (EGO_MPS / 2.0, EGO_MPS / 12**0.5),
    "half the ego's speed, std 10 m/s": (EGO_MPS / 2.0, EGO_MPS / 2.0),
    "0, std 5 m/s": (0.0, 5.0),
}


def velocity_errors(prior_mps: float, prior_std_mps: float, speed_mps: float, n: int, seed: int) -> np.ndarray:
    """The track's velocity error (estimate minus truth, m/s) after each step's update, float64 [STEPS, n]; NaN where
    the rollout has no track yet."""
    rng = np.random.default_rng(seed)
    detector = camera_detector(NAMES)
    params = tracker.TrackerParams(init_speed_std_x_mps=prior_std_mps)
    tracks = tracker.Tracks.empty((n,))
    errors = np.full((STEPS, n), np.nan)
    for t in range(STEPS):
        ego_x = EGO_MPS * t * DT
        loc_x, loc_z = np.zeros(n), np.full(n, FIRST_RANGE_M + (speed_mps - EGO_MPS) * t * DT)
        view = camera.view(camera.CAR, loc_x, loc_z, -np.pi / 2)
        seen = perceive(detector, np.concatenate([view.salient, view.visible[:, None]], axis=1), rng)
        measured = seen.detected & view.visible
        x_m, z_m = camera.measure(loc_x, loc_z, seen.noise, measured)
        tracks = tracker.update(tracks, measured, ego_x + z_m, x_m, z_m, prior_mps, params)
        errors[t] = np.where(tracks.active, tracks.vx - speed_mps, np.nan)
        tracks = tracker.predict(tracks, DT, params)
    return errors


def settling_time(abs_error: np.ndarray) -> float:
    """The first time (s, from the first step) from which ``abs_error`` [STEPS] stays within the tolerance; inf: not
    within the horizon."""
    off = np.flatnonzero(~(abs_error <= TOLERANCE_MPS))
    if off.size == 0:
        return 0.0
    return float("inf") if off[-1] == STEPS - 1 else (off[-1] + 1) * DT


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--n", type=int, default=2000)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    print(
        f"ego {EGO_MPS:.0f} m/s, a car first seen {FIRST_RANGE_M:.0f} m ahead, {args.n} rollouts of "
        f"{STEPS * DT:.0f} s: "
        f"the time from which the median (90th percentile) velocity error stays within {TOLERANCE_MPS:.0f} m/s, and "
        "the median estimate at 0.5 s and 1.0 s"
    )
    for label, (prior, std) in PRIORS.items():
        cells = []
        for speed in (0.0, EGO_MPS):
            err = velocity_errors(prior, std, speed, args.n, args.seed)
            abs_err = np.abs(err)
            median, q90 = np.nanmedian(abs_err, axis=1), np.nanquantile(abs_err, 0.9, axis=1)
            at = np.nanmedian(err, axis=1) + speed
            cells.append(
                f"car at {speed:2.0f} m/s: {settling_time(median):.1f} s ({settling_time(q90):.1f} s), "
                f"{at[4]:4.1f} / {at[9]:4.1f} m/s"
            )
        print(f"prior {label:34s} " + "; ".join(cells))


if __name__ == "__main__":
    main()
