"""PyBullet's own InvertedPendulumSwingupBulletEnv-v0: record the test fixture, evaluate a policy.

PyBullet is not a dependency of espl-jax (its ``pybullet_envs`` needs the unmaintained ``gym``),
so this script runs in a venv of its own:

    python3 -m venv /tmp/pb && /tmp/pb/bin/pip install pybullet==3.2.7 gym==0.26.2 numpy
    /tmp/pb/bin/python benchmarks/pybullet_swingup.py record
    /tmp/pb/bin/python benchmarks/pybullet_swingup.py evaluate runs/NAME/policy.py [--episodes 100]

``record`` writes ``tests/data/pybullet_swingup.json``, which ``tests/test_envs_mjx.py`` checks
the MJX swing-up against:

* ``rollouts``: three 200-step rollouts, each the joint state ``qpos = [x, theta]``,
  ``qvel = [x_dot, theta_dot]`` before every step and after the last, the normalized actions and
  the rewards: ``paper`` (the InvPendSwingup formula of the ESPL paper's Table 3 in closed loop,
  from a seeded reset; it drives the cart into the rail's end at step 33), ``sine``
  (``0.8 sin(2 pi t / 80)`` open loop) and ``random`` (U(-1, 1) actions, open loop), both from
  ``theta = 3.1415 + 0.05`` at rest;
* ``paper_returns``: the formula's 1000-step return for env seeds 0..19.

The formula is printed in Table 3 as ``4.33 sin(0.17 s1 + 0.14 s2 + 0.49 s3 + 1.76 s4 + 0.33 s4
- 0.29) - 0.65``; the second ``s4`` is read as ``s5`` (theta_dot), the only reading that swings
the pole up (with ``s4`` twice it scores about -940 here), and the action is its tanh.

``evaluate`` plays an exported ``policy.py`` (``act(obs) -> action``) for 1000-step episodes on
env seeds 1000, 1001, ... and prints the mean return.
"""

import argparse
import importlib.util
import json
from pathlib import Path

import numpy as np


class _Registry(dict):
    """gym 0.26's registry is a dict; ``pybullet_envs`` asks for ``registry.env_specs``."""


def make_env():
    """PyBullet's swing-up env. Imported here, after argument parsing, so that ``--help`` works
    without PyBullet (it lives in a venv of its own, see the module docstring)."""
    try:
        import gym.envs.registration as registration
    except ImportError:
        raise SystemExit(
            "error: this script needs PyBullet and gym in a venv of their own: python3 -m venv "
            "/tmp/pb && /tmp/pb/bin/pip install pybullet==3.2.7 gym==0.26.2 numpy"
        ) from None
    registration.registry = _Registry(registration.registry)
    registration.registry.env_specs = registration.registry
    from pybullet_envs.gym_pendulum_envs import InvertedPendulumSwingupBulletEnv

    return InvertedPendulumSwingupBulletEnv()


STEPS = 200
EPISODES = 20


def paper_formula(obs):
    s1, s2, s3, s4, s5 = obs
    z = 4.33 * np.sin(0.17 * s1 + 0.14 * s2 + 0.49 * s3 + 1.76 * s4 + 0.33 * s5 - 0.29) - 0.65
    return np.array([np.tanh(z)])


def joint_state(env):
    x, x_dot = env.robot.slider.current_position()
    theta, theta_dot = env.robot.j1.current_position()
    return [x, theta], [x_dot, theta_dot]


def rollout(env, policy=None, actions=None, theta0=None, seed=0):
    env.seed(seed)
    obs = env.reset()
    if theta0 is not None:
        env.robot.j1.reset_current_position(theta0, 0)
        obs = env.robot.calc_state()
    qpos, qvel, acts, rewards = [], [], [], []
    for t in range(STEPS):
        q, v = joint_state(env)
        qpos.append(q)
        qvel.append(v)
        a = policy(obs) if policy is not None else actions[t]
        obs, r, _, _ = env.step(a)
        acts.append(float(a[0]))
        rewards.append(float(r))
    q, v = joint_state(env)
    qpos.append(q)
    qvel.append(v)
    return {"qpos": qpos, "qvel": qvel, "actions": acts, "rewards": rewards}


def _round(tree):
    """Floats to 9 significant digits (float32 MJX is compared at 1e-6 at best)."""
    if isinstance(tree, dict):
        return {k: _round(v) for k, v in tree.items()}
    if isinstance(tree, list | tuple):
        return [_round(v) for v in tree]
    return float(f"{tree:.9g}") if isinstance(tree, float) else tree


def episode_return(env, policy, seed):
    env.seed(seed)
    obs, total = env.reset(), 0.0
    for _ in range(1000):
        obs, r, _, _ = env.step(np.asarray(policy(obs), np.float64))
        total += r
    return total


def record(env):
    t = np.arange(STEPS)
    rng = np.random.default_rng(0)
    sine = 0.8 * np.sin(2 * np.pi * t / 80.0)[:, None]
    out = {
        "source": "pybullet 3.2.7, pybullet_envs InvertedPendulumSwingupBulletEnv "
        "(benchmarks/pybullet_swingup.py record)",
        "rollouts": {
            "paper": rollout(env, policy=paper_formula),
            "sine": rollout(env, actions=sine, theta0=3.1915),
            "random": rollout(env, actions=rng.uniform(-1, 1, (STEPS, 1)), theta0=3.1915),
        },
    }
    returns = [episode_return(env, paper_formula, seed) for seed in range(EPISODES)]
    out["paper_returns"] = returns
    path = Path(__file__).resolve().parents[1] / "tests" / "data" / "pybullet_swingup.json"
    path.write_text(json.dumps(_round(out), separators=(",", ":")))
    print(f"wrote {path}; paper formula {np.mean(returns):.2f} +- {np.std(returns):.2f}")


def evaluate(env, policy_file, episodes):
    spec = importlib.util.spec_from_file_location("policy", policy_file)
    policy = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(policy)
    returns = [episode_return(env, policy.act, 1000 + i) for i in range(episodes)]
    print(
        f"{policy_file} in PyBullet's InvertedPendulumSwingupBulletEnv, {episodes} episodes: "
        f"{np.mean(returns):.2f} +- {np.std(returns):.2f} (min {np.min(returns):.2f})"
    )


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    sub.add_parser("record", help="write tests/data/pybullet_swingup.json")
    ev = sub.add_parser("evaluate", help="play an exported policy.py")
    ev.add_argument("policy", help="path of an exported policy.py")
    ev.add_argument("--episodes", type=int, default=100)
    args = parser.parse_args()
    env = make_env()
    if args.command == "record":
        record(env)
    else:
        evaluate(env, args.policy, args.episodes)


if __name__ == "__main__":
    main()
