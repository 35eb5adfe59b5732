"""``pemviz/Braking-v0``: registered on ``import pemviz``, a valid gymnasium environment, and with the
scenario's own controller it moves exactly as the braking scenario does for the same detections."""

from __future__ import annotations

import subprocess
import sys
import warnings

import gymnasium as gym
import numpy as np
import pytest
from pemviz import stl
from pemviz.core.detectors import action_log_prob
from pemviz.envs import ENV_ID, MISSED_GAP_M, BasicAgentController, BrakingEnv
from pemviz.pem import load_pem
from pemviz.scenarios.braking.simulator import BrakingScenario

from conftest import REPO

SPEC = stl.parse("G[0,99](d >= 2)")


class ScriptedDetector:
    """Detects iff the script says so at that call: logit +-60 (p = 1 - 9e-27 or 9e-27)."""

    def __init__(self, script: np.ndarray) -> None:
        self.script, self.calls = np.asarray(script, dtype=bool), 0

    def detect_logit(self, obs: np.ndarray) -> np.ndarray:
        a = self.script[min(self.calls, self.script.size - 1)]
        self.calls += 1
        return np.full(np.shape(obs)[0], 60.0 if a else -60.0)


@pytest.fixture(scope="module")
def pem():
    return load_pem()


def episode(env, controller, seed=0):
    obs, info = env.reset(seed=seed)
    controller.reset()
    infos, observations, rewards = [info], [obs], []
    truncated = False
    while not truncated:
        obs, reward, terminated, truncated, info = env.step(controller(obs))
        assert terminated is False
        infos.append(info), observations.append(obs), rewards.append(reward)
    return infos, np.array(observations), np.array(rewards)


def test_import_pemviz_registers_the_env_without_importing_the_simulator_or_torch():
    assert gym.spec(ENV_ID).entry_point == "pemviz.envs:BrakingEnv"
    code = (
        "import sys, pemviz, gymnasium; print(sorted(m for m in ('torch', 'highway_env', 'pemviz.scenarios') "
        "if m in sys.modules), 'pemviz/Braking-v0' in gymnasium.registry)"
    )
    out = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert out.stdout.strip() == "[] True", out.stderr
    # nor gymnasium itself until it is imported (every command is that much faster), and in either order
    code = (
        "import sys, pemviz; print('gymnasium' in sys.modules); import gymnasium; "
        "print('pemviz/Braking-v0' in gymnasium.registry)"
    )
    out = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert out.stdout.split() == ["False", "True"], out.stderr
    code = "import gymnasium, pemviz; print('pemviz/Braking-v0' in gymnasium.registry)"
    out = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert out.stdout.strip() == "True", out.stderr


def test_env_passes_gymnasium_check_env(pem):
    from gymnasium.utils.env_checker import check_env

    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*symmetric and normalized space.*")  # physical units, m/s^2
        check_env(BrakingEnv(pem=pem), skip_render_check=True)


def test_basic_agent_in_the_env_moves_exactly_as_the_braking_scenario_for_the_same_detections(pem):
    script = np.random.default_rng(3).random(101) < 0.6
    env = gym.make(ENV_ID, detector=ScriptedDetector(script), pem=pem)
    infos, observations, rewards = episode(env, BasicAgentController())
    sim = BrakingScenario()
    trace = []
    for t in range(100):
        trace.append(sim.observation())
        sim.step(bool(script[t]))
    trace = np.array(trace)
    got = np.array([[i["gap_m"], i["ego_speed_mps"], i["lead_speed_mps"]] for i in infos[:100]])
    np.testing.assert_array_equal(got, trace[:, :3])  # bit for bit
    assert [i["detected"] for i in infos] == list(script)
    np.testing.assert_array_equal(observations[:100, 0], script[:100].astype(float))
    np.testing.assert_array_equal(observations[:100, 1], np.where(script[:100], trace[:, 0], MISSED_GAP_M))
    crashed = stl.robustness(SPEC, {"d": trace[:, 0]}) < 0.0  # the spec's failure event, from the scenario
    assert rewards.sum() == (-1.0 if crashed else 0.0)


def test_always_detected_stops_at_the_calibrated_gap_and_never_detected_crashes_once(pem):
    infos, _, rewards = episode(
        gym.make(ENV_ID, detector=ScriptedDetector(np.ones(101)), pem=pem), BasicAgentController()
    )
    gaps = np.array([i["gap_m"] for i in infos[:100]])
    assert gaps.min() == pytest.approx(5.95, abs=0.15)  # spec section 1: CARLA stops 5.95 m behind
    assert rewards.sum() == 0.0
    infos, _, rewards = episode(
        gym.make(ENV_ID, detector=ScriptedDetector(np.zeros(101)), pem=pem), BasicAgentController()
    )
    gaps = np.array([i["gap_m"] for i in infos[:100]])
    first = int(np.argmax(gaps < 2.0))
    assert rewards.sum() == -1.0 and rewards[first - 1] == -1.0  # the step that brought the gap below 2 m
    assert min(gaps) < 2.0 and infos[-1]["crashed"]


def test_a_swapped_controller_changes_the_outcome():
    """With a detector that misses every other step, the scenario's controller (its brake does not latch)
    crashes; a user's latched emergency brake (6 m/s^2 from the first sight within 12 m) does not."""

    def env():
        return BrakingEnv(detector=ScriptedDetector(np.arange(101) % 2 == 0))

    class LatchedBrake:
        def reset(self):
            self.braking = False

        def __call__(self, obs):
            self.braking = self.braking or bool(obs[0] and obs[1] < 12.0)
            return np.array([-6.0 if self.braking else 0.0])

    infos, _, rewards = episode(env(), LatchedBrake())
    gaps = np.array([i["gap_m"] for i in infos[:100]])
    assert rewards.sum() == 0.0 and gaps.min() > 2.0
    infos, _, rewards = episode(env(), BasicAgentController())  # the scenario's controller with the same detector
    assert rewards.sum() == -1.0  # misses every other step: the non-latched brake hands back to the PID


def test_pem_detections_are_seeded_and_carry_their_log_probabilities(pem):
    env = BrakingEnv(pem=pem)
    a, _, _ = episode(env, BasicAgentController(), seed=7)
    b, _, _ = episode(env, BasicAgentController(), seed=7)
    assert [i["detected"] for i in a] == [i["detected"] for i in b]
    gaps = np.array([i["gap_m"] for i in a])
    detected = np.array([i["detected"] for i in a])
    expected = action_log_prob(pem.logit_at_gap(gaps), detected)
    np.testing.assert_allclose([i["log_p"] for i in a], expected, rtol=0, atol=1e-15)
    np.testing.assert_array_equal([i["log_q"] for i in a], [i["log_p"] for i in a])  # sampled from the PEM
    assert detected.mean() > 0.9  # the PEM detects 98-99.5 % of the time
    with pytest.raises(RuntimeError, match="episode over after 100 steps"):
        env.step(np.zeros(1))
