"""The results pages are generated: ``benchmarks/report.py --check`` passes on the committed tree
and fails, naming the file, once a generated table is edited by hand (in a copy of the tree)."""

from __future__ import annotations

import ast
import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
REPORT = ROOT / "benchmarks" / "report.py"


def check(root: Path) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, str(REPORT), "--check", "--root", str(root)],
        capture_output=True,
        text=True,
        timeout=60,
    )


@pytest.fixture
def tree(tmp_path: Path) -> Path:
    """A copy of what the report reads and writes."""
    for name in ("results", "docs"):
        shutil.copytree(ROOT / name, tmp_path / name)
    shutil.copy(ROOT / "README.md", tmp_path / "README.md")
    return tmp_path


def test_committed_docs_are_what_the_results_generate():
    done = check(ROOT)
    assert done.returncode == 0, done.stderr


@pytest.mark.parametrize(
    ("path", "old", "new"),
    [
        ("docs/single_task.md", "**5/5** ≥ 990", "**4/5** ≥ 990"),
        # The meta-RL headline table's header, which new results do not change.
        ("docs/meta_rl.md", "| family | CSP |", "| family | CSP (edited) |"),
        ("README.md", "| family | CSP |", "| family | CSP (edited) |"),
    ],
)
def test_a_hand_edited_table_fails_the_check(tree: Path, path: str, old: str, new: str):
    text = (tree / path).read_text()
    assert old in text
    (tree / path).write_text(text.replace(old, new, 1))
    done = check(tree)
    assert done.returncode != 0
    assert path in done.stderr


def test_a_missing_plot_fails_the_check(tree: Path):
    (tree / "docs" / "single_task.png").unlink()
    done = check(tree)
    assert done.returncode != 0 and "docs/single_task.png" in done.stderr


def test_a_new_results_file_of_the_same_schema_shows_up(tree: Path):
    # A later sweep that writes a results file of the same shape lands on its page.
    (tree / "results" / "ablation_cartpole.json").write_text(
        '{"kind": "ablation", "command": "python benchmarks/ablation.py", "commit": "abc1234", '
        '"date": "2026-12-07", "machine": {"cpus": 2}, '
        '"rows": [{"env": "cartpole", "variant": "plain", "seed": 0, "return": 512.5}]}\n'
    )
    done = check(tree)
    assert done.returncode != 0 and "docs/ablations.md" in done.stderr
    subprocess.run([sys.executable, str(REPORT), "--root", str(tree)], check=True, timeout=60)
    page = (tree / "docs" / "ablations.md").read_text()
    assert "512.50" in page and "Not yet run" not in page
    assert check(tree).returncode == 0


def test_a_probe_is_on_its_page_but_not_in_the_readme(tree: Path):
    # "headline": false keeps a run of another budget out of the README's headline table.
    probe = json.loads((tree / "results" / "walker2d_params_10x_probe.json").read_text())
    assert probe["headline"] is False
    returns = [r["test_return"] for r in probe["rows"]]
    cell = f"[{min(returns):.2f}, {max(returns):.2f}]"  # the headline cell's seed interval
    page, readme = (tree / "docs" / "meta_rl.md").read_text(), (tree / "README.md").read_text()
    assert f"{returns[0]:.2f}" in page and cell not in readme
    probe["headline"] = True
    (tree / "results" / "walker2d_params_10x_probe.json").write_text(json.dumps(probe))
    subprocess.run([sys.executable, str(REPORT), "--root", str(tree)], check=True, timeout=60)
    assert cell in (tree / "README.md").read_text()


def test_a_row_marked_off_the_headline_stays_on_its_page(tree: Path):
    # "headline": false on one row (a run of an older config in a file of several envs).
    path = tree / "results" / "single_task_single_runs.json"
    data = json.loads(path.read_text())
    walker = next(
        r for r in data["rows"] if r["env"] == "bipedalwalker" and r["actor"] == "symbolic"
    )
    # Put the row on the headline, as the only bipedalwalker run, then take it off.
    walker.pop("headline", None)
    path.write_text(json.dumps(data))
    for other in (tree / "results").glob("bipedalwalker_*.json"):
        other.unlink()
    subprocess.run([sys.executable, str(REPORT), "--root", str(tree)], check=True, timeout=60)
    cell = f"| bipedalwalker | 1 run (seed 0) | {walker['return']:.2f} |"
    assert cell in (tree / "README.md").read_text()
    walker["headline"] = False
    path.write_text(json.dumps(data))
    subprocess.run([sys.executable, str(REPORT), "--root", str(tree)], check=True, timeout=60)
    assert cell not in (tree / "README.md").read_text()
    assert f"{walker['return']:.2f}" in (tree / "docs" / "single_task.md").read_text()


def test_the_meta_rl_deployment_table_sits_beside_the_papers(tree: Path):
    # deploy.py --run CSP_DIR rows of a family: CSP (median test task), PEARL, Hyper per impl.
    def row(method: str, impl: str, flops: int, ms: float, **extra) -> str:
        fields = {
            "env": "hopper_params",
            "family": True,
            "method": method,
            "impl": impl,
            "policy": f"{method} (x)",
            "flops_per_robot_step": flops,
            "ms_per_step": ms,
        }
        return json.dumps({**fields, **extra})

    csp = {"tasks": 10, "per_task_flops": [40] * 10, "per_task_ms": [1.5] * 10}
    rows = [row("CSP", "numpy", 40, 1.25, **csp), row("CSP", "jax", 40, 0.75, **csp)]
    rows += [row("PEARL", i, 372309, 90.0) for i in ("numpy", "jax")]
    rows += [row("Hyper", i, 7433, 9.0) for i in ("numpy", "jax")]
    (tree / "results" / "deploy_meta_rl.json").write_text(
        '{"command": "python benchmarks/deploy.py --run x", "rows": [' + ", ".join(rows) + "]}\n"
    )
    subprocess.run([sys.executable, str(REPORT), "--root", str(tree)], check=True, timeout=60)
    page = (tree / "docs" / "deployment.md").read_text()
    line = next(ln for ln in page.splitlines() if ln.startswith("| hopper_params |"))
    # ours (k FLOPs / numpy ms / JAX ms) beside the paper's (0.51/4.13, 186.9/26.6, 4.1/17.2)
    assert "| 0.04 / 1.25 / 0.75 | 0.51 / 4.13 |" in line
    assert (
        "| 372 / 90 / 90 | 186.90 / 26.60 |" in line and "| 7.43 / 9 / 9 | 4.10 / 17.20 |" in line
    )
    assert "10 tasks" in line


def test_the_readme_shows_the_api_tests_example_verbatim():
    source = (ROOT / "tests" / "test_api.py").read_text()
    example = next(
        node.value.value
        for node in ast.parse(source).body
        if isinstance(node, ast.Assign) and getattr(node.targets[0], "id", None) == "README_EXAMPLE"
    )
    assert f"```python\n{example}```" in (ROOT / "README.md").read_text()


def test_the_ablation_summary_puts_each_seed_beside_the_papers_table_5(tree: Path):
    page = (tree / "docs" / "ablations.md").read_text()
    assert "| pendulum | -147.25 / -155.30 / -151.47 (paper -151.72) |" in page
    path = tree / "results" / "ablation_pendulum.json"
    data = json.loads(path.read_text())
    first = next(r for r in data["rows"] if r["variant"] == "ESPL" and r["seed"] == 0)
    first["return"] = -140.5
    path.write_text(json.dumps(data))
    subprocess.run([sys.executable, str(REPORT), "--root", str(tree)], check=True, timeout=60)
    page = (tree / "docs" / "ablations.md").read_text()
    assert "| pendulum | -140.50 / -155.30 / -151.47 (paper -151.72) |" in page
