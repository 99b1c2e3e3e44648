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
same with ``--env`` a task family: CSP, CSP_p, CSP_d, CSP_l1, scored by the test return under
PEARL's protocol. Consecutive seeds run as one vmapped ``--seeds N`` run (``run_block``: same
keys as the single runs, other numbers).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

from env_throughput import write_result

from espl_jax.envs import is_family

# variant → the config keys it changes (ESPL itself: the shipped config as it is).
VARIANTS = {
    "ESPL": {},
    "ESPL_p": {"layout": "plain"},
    "ESPL_d": {"layout": "dense"},
    "ESPL_l1": {"selector": "l1"},
}
# CSP's ablation (paper App. "Ablation Study for Meta-RL", Figure "ablation_result"): the same
# changes to a task family's shipped CSP config.
META_VARIANTS = {
    "CSP": {},
    "CSP_p": {"layout": "plain"},
    "CSP_d": {"layout": "dense"},
    "CSP_l1": {"selector": "l1"},
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


def blocks(seeds: list[int]) -> list[list[int]]:
    """Runs of consecutive seeds: each becomes one ``--seeds N --seed FIRST`` run."""
    out: list[list[int]] = []
    for s in sorted(set(seeds)):
        if out and s == out[-1][-1] + 1:
            out[-1].append(s)
        else:
            out.append([s])
    return out


def run_dir_for(out: Path, env: str, variant: str, block: list[int]) -> Path:
    tail = f"s{block[0]}" if len(block) == 1 else f"s{block[0]}-{block[-1]}"
    return out / f"{env}-{variant}-{tail}"


def run_block(env: str, variant: str, changes: dict, block: list[int], out: Path) -> Path:
    """One ``--seeds N --seed block[0]`` run: its seed ``block[0] + i`` has the keys of the
    ``--seed block[0]+i`` run (espl_jax/keys.py) and collects the same first iteration, but the
    vmapped matrix products round differently and training amplifies that (cartpole: critic loss
    equal to 5e-6 after one update, 20 % apart after 20), so its returns are another draw of
    that seed, not the single run's. Every variant is run the same way."""
    run_dir = run_dir_for(out, env, variant, block)
    if (run_dir / "eval.json").is_file():
        return run_dir
    cmd = [sys.executable, "-m", "espl_jax.train", "--no-progress"]
    if run_dir.exists():  # a killed sweep: the run continues with the config it saved
        cmd += ["--resume", str(run_dir)]
    else:
        config = out / f"{env}-{variant}.yaml"
        config.write_text("".join(f"{k}: {v}\n" for k, v in changes.items()))
        cmd += ["--env", env, "--seed", str(block[0]), "--seeds", str(len(block))]
        cmd += ["--config", str(config), "--out", str(run_dir)]
    subprocess.run(cmd, check=True)
    return run_dir


def seed_rows(run_dir: Path, first_seed: int) -> list[dict]:
    """(seed, return, length) per seed of a finished run: the exported formula's evaluation for
    a single task, the test return under PEARL's protocol for a task family."""
    record = json.loads((run_dir / "eval.json").read_text())
    rows = []
    for entry in record["per_seed"]:
        if "test_return" in entry:
            ret, reference = entry["test_return"], None
            length = entry.get(
                "length", record.get("length") if len(record["per_seed"]) == 1 else None
            )
        else:
            ret = entry["jax_eval"]["mean"]
            reference = (entry.get("reference_eval") or {}).get("mean")
            length = entry.get("length")
        rows.append(
            {
                "seed": first_seed + entry["seed"],
                "return": ret,
                "reference_return": reference,
                "length": length,
                "run": run_dir.name,
            }
        )
    return rows


def block_of(run_dir: Path) -> list[int]:
    """The seeds of a run directory named by ``run_dir_for``."""
    lo, _, hi = run_dir.name.rsplit("-s", 1)[1].partition("-")
    return list(range(int(lo), int(hi or lo) + 1))


def existing_runs(out: Path, env: str, variant: str) -> dict[int, Path]:
    """Seeds already finished in ``out`` by earlier blocks (so a sweep can be widened)."""
    found: dict[int, Path] = {}
    for run_dir in out.glob(f"{env}-{variant}-s*"):
        if (run_dir / "eval.json").is_file():
            found.update(dict.fromkeys(block_of(run_dir), run_dir))
    return found


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--env", required=True)
    parser.add_argument("--seeds", default="0-2", help="e.g. 0-2 or 0,3")
    parser.add_argument(
        "--variants",
        help=f"comma-separated (default: all; single task: {', '.join(VARIANTS)}; "
        f"task family: {', '.join(META_VARIANTS)})",
    )
    parser.add_argument("--out", type=Path, required=True, help="folder for the run directories")
    parser.add_argument("--json", required=True, help="results file to write")
    parser.add_argument(
        "--finished-only",
        action="store_true",
        help="write the rows of the runs already finished in --out and start none (a sweep "
        "still under way, or killed)",
    )
    args = parser.parse_args(argv)
    table = META_VARIANTS if is_family(args.env) else VARIANTS
    variants = args.variants.split(",") if args.variants else list(table)
    unknown = sorted(set(variants) - set(table))
    if unknown:
        parser.error(f"unknown variants {unknown} for {args.env}; known: {', '.join(table)}")
    args.out.mkdir(parents=True, exist_ok=True)
    paper = PAPER_TABLE.get(args.env)
    seeds = seeds_arg(args.seeds)
    rows = []
    for variant in variants:
        done = existing_runs(args.out, args.env, variant)
        for block in [] if args.finished_only else blocks([s for s in seeds if s not in done]):
            run_dir = run_block(args.env, variant, table[variant], block, args.out)
            done.update({s: run_dir for s in block})
        for run_dir in sorted(set(done.values())):
            for row in seed_rows(run_dir, block_of(run_dir)[0]):
                if row["seed"] not in seeds:
                    continue
                row = {"env": args.env, "variant": variant, "changes": table[variant], **row}
                row["paper"] = None if paper is None else paper[list(table).index(variant)]
                rows.append(row)
                print(json.dumps(row), flush=True)
    rows.sort(key=lambda r: (variants.index(r["variant"]), r["seed"]))
    write_result(args.json, rows, argv, script="benchmarks/ablation.py")


if __name__ == "__main__":
    main()
