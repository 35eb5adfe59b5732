"""A user's scene written from the guide alone (a helper of tests/test_user_scene_walls.py): two pedestrians ahead of
a car, the second hidden behind a van until it is within 25 m (its detection logit -inf), a camera that reads the
object rows' ``visible`` column (not the first), the first observation named ``dist_m`` (not ``gap_m``), objects of
its own names and no drawing. The car brakes at 6 m/s^2 for good once a pedestrian is measured within 20 m."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pemviz import stl
from pemviz.core.detector_noise import noise_log_density, noise_quantile
from pemviz.core.problems import Problem, rollout_functions
from pemviz.scenarios.registry import Scenario

DT, T = 0.1, 40
PEDESTRIANS_M = (30.0, 34.0)


@dataclass(frozen=True)
class CrosswalkParams:
    speed_mps: float = 10.0

    def __post_init__(self) -> None:
        if not 1.0 <= self.speed_mps <= 20.0:
            raise ValueError(f"CrosswalkParams: speed_mps must be in [1, 20], got {self.speed_mps}")


class Crosswalk:
    observation_names = ("dist_m", "speed_mps")
    object_names = ("range_m", "visible")
    n_objects = 2

    def __init__(self, n: int, speed_mps: float = 10.0) -> None:
        self.x, self.v, self.braking = np.zeros(n), np.full(n, speed_mps), np.zeros(n, bool)

    def observation(self) -> np.ndarray:
        return np.stack([PEDESTRIANS_M[0] - self.x, self.v], axis=1)

    def objects(self) -> np.ndarray:
        ranges = np.asarray(PEDESTRIANS_M) - self.x[:, None]
        visible = np.stack([np.ones_like(self.x), (ranges[:, 1] < 25.0).astype(float)], axis=1)
        return np.stack([ranges, visible], axis=-1)

    def step(self, detected: np.ndarray, noise: np.ndarray | None = None) -> None:
        measured = self.objects()[:, :, 0] + (0.0 if noise is None else noise[:, :, 0])
        self.braking |= (detected & (measured <= 20.0)).any(axis=1)
        self.v = np.where(self.braking, np.maximum(self.v - 6.0 * DT, 0.0), self.v)
        self.x = self.x + self.v * DT


class Camera:
    noise_names, noise_family, noise_df = ("range_error_m",), "normal", None

    def detect_logit(self, rows: np.ndarray) -> np.ndarray:
        return np.where(rows[:, 1] > 0.5, 4.0 - rows[:, 0] / 4.0, -np.inf)  # hidden: never detected

    def noise_params(self, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return np.zeros((len(rows), 1)), np.log(0.1 * np.maximum(rows[:, :1], 1.0))

    def noise_from_uniforms(self, rows: np.ndarray, u: np.ndarray) -> np.ndarray:
        return noise_quantile(self.noise_family, self.noise_df, *self.noise_params(rows), u)

    def noise_log_prob(self, rows: np.ndarray, noise: np.ndarray) -> np.ndarray:
        return noise_log_density(self.noise_family, self.noise_df, *self.noise_params(rows), noise)


def crosswalk_problem(config: object = None, params: CrosswalkParams | None = None) -> Problem:
    p = params or CrosswalkParams()
    run, stream, resume = rollout_functions(lambda n: Crosswalk(n, p.speed_mps), T)
    return Problem(
        "crosswalk",
        run,
        Camera(),
        stl.parse(f"G[0,{T - 1}](d >= 2)"),
        signals={"d": "dist_m"},
        h_scale=30.0,
        window=28.0,
        stream=stream,
        branch=resume,
        n_objects=2,
        object_labels=("pedestrian A", "pedestrian B"),
    )


SCENARIO = Scenario(
    "user-crosswalk", "two pedestrians, the second hidden behind a van at first", CrosswalkParams, crosswalk_problem
)
