"""How each seed's deterministic policy ends its CartPole episodes: the cart off the track
(|x| > x_threshold) or the pole fallen (|θ| > θ_threshold), from a run's newest checkpoint.

    python benchmarks/cartpole_failures.py RUN_DIR [--episodes 20]

Plays the network under the eval mask (the exported formula's mask; all paths for an unpruned
network) with deterministic actions (``Actor.deterministic``) in the JAX env with its default
params, and prints per seed the mean episode length and how many episodes each condition ended.
Used for the cartpole diagnosis in the README ("Across seeds"). Not part of the test suite.
"""

import argparse

import jax
import jax.numpy as jnp
import numpy as np

from espl_jax import rollout, run
from espl_jax.seeds import take


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run_dir", help="a cartpole run directory")
    parser.add_argument("--episodes", type=int, default=20)
    args = parser.parse_args()
    trainer, state, step = run.load_run(args.run_dir)
    env, params, actor = trainer.env, trainer.env.default_params, trainer.actor
    print(f"{args.run_dir}: checkpoint {step}, {args.episodes} episodes per seed")
    for s in range(jax.tree.leaves(state.actor)[0].shape[0]):
        policy = actor.at(take(state.actor, s), jnp.zeros((0,)))
        mask = actor.eval_mask(policy)

        def episode(key, policy=policy, mask=mask):
            def body(carry, _):
                obs, st, done, length = carry
                action = actor.deterministic(policy, mask, obs)
                obs2, st2, _, term, trunc, _ = env.step(key, st, action, params)
                # Freeze the episode at its end, so the final obs says why it ended.
                obs, st = rollout.where(done, (obs, st), (obs2, st2))
                return (obs, st, done | term | trunc, length + ~done), None

            obs, st = env.reset(key, params)
            start = (obs, st, jnp.array(False), jnp.array(0))
            (obs, _, _, length), _ = jax.lax.scan(body, start, None, env.horizon)
            return obs, length

        keys = jax.random.split(jax.random.PRNGKey(7), args.episodes)
        obs, length = map(np.asarray, jax.jit(jax.vmap(episode))(keys))
        cart = np.abs(obs[:, 0]) > params.x_threshold
        pole = np.abs(obs[:, 2]) > params.theta_threshold_radians
        print(
            f"seed {s}: mean length {length.mean():.0f}; ended by the cart {int(cart.sum())}, "
            f"by the pole {int(pole.sum())}, not ended {int((~cart & ~pole).sum())}"
        )


if __name__ == "__main__":
    main()
