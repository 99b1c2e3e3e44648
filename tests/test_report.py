"""The results pages are generated: ``benchmarks/report.py --check`` passes on the committed tree
and fails, naming the file, once a generated table is edited by hand (in a copy of the tree)."""

from __future__ import annotations

import ast
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
        ("docs/meta_rl.md", "188.37", "198.37"),
        ("README.md", "188.37", "189.37"),
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


def test_the_readme_shows_the_api_tests_example_verbatim():
    source = (ROOT / "tests" / "test_api.py").read_text()
    example = next(
        node.value.value
        for node in ast.parse(source).body
        if isinstance(node, ast.Assign) and getattr(node.targets[0], "id", None) == "README_EXAMPLE"
    )
    assert f"```python\n{example}```" in (ROOT / "README.md").read_text()
