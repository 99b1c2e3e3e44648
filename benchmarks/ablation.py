"""The paper's single-task ablation (§5.3, Table "Ablation results for single-task RL"), run:
ESPL against ESPL_p (plain layout), ESPL_d (densely connected, operators not arranged) and
ESPL_l1 (L1 minimisation instead of the path selector), each with the env's shipped config::

    python benchmarks/ablation.py --env cartpole --seeds 0-2 --out /tmp/ablation \\
        --json results/ablation_cartpole.json

Each variant × seed is one ``python -m espl_jax.train`` run (``--seed S``, so a seed's run is
the README's command for that seed); runs already finished in ``--out`` are reused, so a
killed sweep continues where it stopped. The results file has one row per variant and seed
(the exported formula's return and length) and the paper's value for the variant;
``python benchmarks/report.py`` shows it on docs/ablations.md. CSP's meta-RL ablation is the
same with ``--env`` a task family (layouts ``csp`` and the plain/dense ones).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

from env_throughput import write_result

# variant → the config keys it changes (ESPL itself: the shipped config as it is).
VARIANTS = {
    "ESPL": {},
    "ESPL_p": {"layout": "plain"},
    "ESPL_d": {"layout": "dense"},
    "ESPL_l1": {"selector": "l1"},
}
# The paper's Table (single task), per env: ESPL, ESPL_p, ESPL_d, ESPL_l1.
PAPER_TABLE = {
    "cartpole": (1000, 1000, 1000, 1000),
    "mountaincar": (94.02, 93.69, 93.83, 94.17),
    "pendulum": (-151.72, -183.16, -144.08, -163.54),
    "inverted_double_pendulum": (9359.9, 9357.6, 9197.44, 8771.18),
    "inverted_pendulum_swingup": (890.36, 844.84, 890.01, 865.38),
    "lunarlander": (283.56, 263.95, 277.36, 271.69),
    "hopper": (2442.48, 2003.24, 2316.54, 1546.35),
    "bipedalwalker": (309.43, -11.63, 298.50, 6.81),
}


def seeds_arg(text: str) -> list[int]:
    if "-" in text:
        lo, hi = text.split("-")
        return list(range(int(lo), int(hi) + 1))
    return [int(s) for s in text.split(",")]


def run_one(env: str, variant: str, seed: int, out: Path) -> Path:
    run_dir = out / f"{env}-{variant}-s{seed}"
    if (run_dir / "eval.json").is_file():
        return run_dir
    config = out / f"{env}-{variant}.yaml"
    config.write_text("".join(f"{k}: {v}\n" for k, v in VARIANTS[variant].items()))
    cmd = [sys.executable, "-m", "espl_jax.train", "--env", env, "--seed", str(seed)]
    cmd += ["--config", str(config), "--no-progress"]
    cmd += ["--resume", str(run_dir)] if run_dir.exists() else ["--out", str(run_dir)]
    subprocess.run(cmd, check=True)
    return run_dir


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--env", required=True)
    parser.add_argument("--seeds", default="0-2", help="e.g. 0-2 or 0,3")
    parser.add_argument("--variants", default=",".join(VARIANTS), help="comma-separated")
    parser.add_argument("--out", type=Path, required=True, help="folder for the run directories")
    parser.add_argument("--json", required=True, help="results file to write")
    args = parser.parse_args(argv)
    variants = args.variants.split(",")
    unknown = sorted(set(variants) - set(VARIANTS))
    if unknown:
        parser.error(f"unknown variants {unknown}; known: {', '.join(VARIANTS)}")
    args.out.mkdir(parents=True, exist_ok=True)
    paper = PAPER_TABLE.get(args.env)
    rows = []
    for variant in variants:
        for seed in seeds_arg(args.seeds):
            record = json.loads(
                (run_one(args.env, variant, seed, args.out) / "eval.json").read_text()
            )
            rows.append(
                {
                    "env": args.env,
                    "variant": variant,
                    "changes": VARIANTS[variant],
                    "seed": seed,
                    "return": record["jax_eval"]["mean"],
                    "reference_return": (record.get("reference_eval") or {}).get("mean"),
                    "length": record.get("length"),
                    "paper": None if paper is None else paper[list(VARIANTS).index(variant)],
                }
            )
            print(json.dumps(rows[-1]), flush=True)
    write_result(args.json, rows, argv, script="benchmarks/ablation.py")


if __name__ == "__main__":
    main()
