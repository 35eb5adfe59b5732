"""The braking scenario as a gymnasium environment, ``pemviz/Braking-v0``: bring your own controller.

``import pemviz`` registers it (by entry-point string) as soon as gymnasium is imported::

    import gymnasium as gym
    import pemviz

    env = gym.make("pemviz/Braking-v0")                  # detections drawn from the shipped PEM
    controller = pemviz.envs.BasicAgentController()      # the scenario's own ego controller
    obs, info = env.reset(seed=0)
    controller.reset()
    for _ in range(100):
        obs, reward, terminated, truncated, info = env.step(controller(obs))

The scenario is Innes & Ramamoorthy (2022)'s automated braking
(:class:`pemviz.scenarios.braking.simulator.BrakingScenario`) with the agent as the ego's controller:

- **observation** float64 [3]: ``(detected, seen_gap_m, ego_speed_mps)``: 1.0 if the detector sees the lead (else
  0.0); the gap in metres when detected, -1.0 when missed; the ego's speed in m/s.
- **action** float64 [1]: the ego's acceleration command in m/s^2, clipped to [-27.5, 4.0]; the ego never reverses
  and stops in contact (gap <= 0.7 m).
- **detector**: ``detected`` iff ``u <= p(detect | state)``, ``u`` from ``np_random``, ``p`` from ``detector``
  (default: the PEM); ``info`` carries ``log_p`` and ``log_q`` (nats) for importance weights.
- **reward** -1.0 at the step the gap first drops below 2 m, else 0.0; never terminated, truncated after 100 actions
  of dt = 0.05 s. ``info`` also holds ``gap_m``, ``ego_speed_mps``, ``lead_speed_mps``, ``crashed``.

With :class:`BasicAgentController` the ego moves exactly as in
:class:`~pemviz.scenarios.braking.simulator.BrakingScenario` for the same detections."""

from __future__ import annotations

import math
from typing import Any

import gymnasium as gym
import numpy as np

ENV_ID = "pemviz/Braking-v0"
MISSED_GAP_M = -1.0
"""``seen_gap_m`` when the detector misses the lead."""


def register_envs() -> None:
    """Register :data:`ENV_ID` with gymnasium (idempotent; imports nothing else)."""
    if ENV_ID not in gym.registry:
        gym.register(id=ENV_ID, entry_point="pemviz.envs:BrakingEnv")


class BasicAgentController:
    """The braking scenario's ego controller as a policy ``obs [3] -> acceleration [1]`` (m/s^2):
    :func:`pemviz.scenarios.braking.simulator.ego_acceleration` on what it observes. Call :meth:`reset` with each
    episode."""

    def __init__(self, params: Any = None) -> None:
        from pemviz.scenarios.braking.simulator import BrakingParams

        self.params = params or BrakingParams()
        self.reset()

    def reset(self) -> None:
        from pemviz.scenarios.braking.simulator import initial_controller_state

        self._ctrl = initial_controller_state(1)

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        from pemviz.scenarios.braking.simulator import ego_acceleration

        detected = bool(obs[0] >= 0.5)
        gap = float(obs[1]) if detected else math.inf  # a missed lead is nowhere (no emergency brake)
        accel, self._ctrl = ego_acceleration(
            self.params, np.array([detected]), np.array([gap]), np.array([float(obs[2])]), self._ctrl
        )
        return np.asarray(accel, dtype=np.float64)


class BrakingEnv(gym.Env):
    """``pemviz/Braking-v0`` (module docstring): the braking scenario with the ego's controller as the agent.

    Args:
        detector: draws the detections (a :class:`pemviz.core.detectors.Detector`: logit of p(detect) from the
            observation [M, 3] = (gap_m, ego speed, lead speed)); default the PEM itself.
        pem: the target PEM (name or path, :func:`pemviz.pem.load_pem`; default the shipped one), or a
            :class:`pemviz.pem.PEM`; gives ``info["log_p"]``.
        params: the scenario's constants (:class:`pemviz.scenarios.braking.simulator.BrakingParams`)."""

    metadata: dict[str, Any] = {"render_modes": []}
    observation_space: gym.spaces.Box
    action_space: gym.spaces.Box

    def __init__(self, detector: Any = None, pem: Any = None, params: Any = None) -> None:
        from pemviz.core.detectors import PEMDetector
        from pemviz.pem import load_pem
        from pemviz.scenarios.braking.simulator import BrakingParams, BrakingScenario

        self.params = params or BrakingParams()
        self.target = PEMDetector(pem if pem is not None and not isinstance(pem, str) else load_pem(pem))
        self.detector = detector if detector is not None else self.target
        self.sim = BrakingScenario(self.params)
        p = self.params
        self.observation_space = gym.spaces.Box(
            low=np.array([0.0, MISSED_GAP_M, 0.0]), high=np.array([1.0, 1000.0, 40.0]), dtype=np.float64
        )
        self.action_space = gym.spaces.Box(
            low=-max(p.brake_decel_mps2), high=p.throttle_accel0_mps2, shape=(1,), dtype=np.float64
        )
        self._crashed = False

    def _detect(self) -> tuple[np.ndarray, dict[str, Any]]:
        from scipy.special import log_expit

        from pemviz.core.detectors import action_log_prob

        state = self.sim.observation()
        o = state[None, :]
        q_logit = self.detector.detect_logit(o)
        p_logit = q_logit if self.detector is self.target else self.target.detect_logit(o)
        detected = bool(math.log(self.np_random.random()) <= float(log_expit(q_logit)[0]))
        a = np.array([detected])
        obs = np.array([float(detected), state[0] if detected else MISSED_GAP_M, state[1]], dtype=np.float64)
        info = {
            "gap_m": float(state[0]),
            "ego_speed_mps": float(state[1]),
            "lead_speed_mps": float(state[2]),
            "detected": detected,
            "log_p": float(action_log_prob(p_logit, a)[0]),
            "log_q": float(action_log_prob(q_logit, a)[0]),
            "crashed": self._crashed,
            "step": self.sim.t,
        }
        return np.clip(obs, self.observation_space.low, self.observation_space.high), info

    def reset(self, *, seed: int | None = None, options: dict | None = None) -> tuple[np.ndarray, dict]:
        super().reset(seed=seed)
        self.sim.reset()
        self._crashed = False
        return self._detect()

    def snapshot(self) -> tuple:
        """The episode's whole state: the scenario's (:meth:`BrakingScenario.snapshot`, a deep copy of the
        highway-env vehicles), the crash flag and the detector stream's generator state."""
        import copy

        return self.sim.snapshot(), self._crashed, copy.deepcopy(self.np_random.bit_generator.state)

    def restore(self, state: tuple) -> None:
        """Put back a :meth:`snapshot`: the same actions then give the same observations, rewards and infos."""
        sim_state, self._crashed, rng_state = state
        self.sim.restore(sim_state)
        self.np_random.bit_generator.state = rng_state

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict]:
        """Apply the acceleration command (m/s^2) for dt seconds, then draw the next detection.

        Raises:
            RuntimeError: stepping after the episode ended (call ``reset``)."""
        sim, p = self.sim, self.params
        if sim.done:
            raise RuntimeError(f"{ENV_ID}: episode over after {p.n_steps} steps; call reset()")
        accel = float(
            np.clip(
                np.asarray(action, dtype=np.float64).reshape(-1)[0], self.action_space.low[0], self.action_space.high[0]
            )
        )
        v, gap = sim.ego.speed, sim.gap_m
        accel = max(accel, -v / p.dt_s)  # the ego never reverses
        if gap <= p.contact_gap_m:  # collision: the ego is stopped (as ego_acceleration does)
            accel = -v / p.dt_s
        # BrakingScenario.step with the agent's acceleration
        sim.ego.act({"steering": 0.0, "acceleration": accel})
        sim.lead.act({"steering": 0.0, "acceleration": float(sim._lead_accel[sim.t])})
        sim.ego.step(p.dt_s)
        sim.lead.step(p.dt_s)
        sim.ego.speed = max(sim.ego.speed, 0.0)
        sim.t += 1
        reward = 0.0
        if not self._crashed and sim.t < p.n_steps and sim.gap_m < p.crash_gap_m:  # states 0..T-1, as the spec
            self._crashed, reward = True, -1.0
        obs, info = self._detect()
        return obs, reward, False, sim.done, info


register_envs()  # importing this module registers the environment too (``import pemviz`` alone waits for gymnasium)
