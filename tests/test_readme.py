"""The README's Python example runs as written (the real simulator, the shipped checkpoint)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
import torch

README = Path(__file__).resolve().parents[1] / "README.md"


@pytest.mark.sim
def test_readme_python_example_runs():
    blocks = re.findall(r"```python\n(.*?)```", README.read_text(), flags=re.S)
    assert blocks, "the README has no Python example"
    namespace: dict = {}
    previous = torch.get_num_threads()
    try:
        exec(compile(blocks[0], str(README), "exec"), namespace)  # noqa: S102  (our own README)
    finally:
        torch.set_num_threads(previous)
    controller, twist = namespace["controller"], namespace["twist"]
    assert twist.shape == (1, 6) and twist.dtype == torch.float32 and torch.isfinite(twist).all()
    assert controller.describe(0)["mode"] in ("shared", "autonomous", "user_only")
    namespace["env"].close()


def test_every_script_the_docs_name_exists():
    """Paths (or patterns) under ``scripts/`` and ``benchmarks/`` named in the README, docs/ or a docstring exist
    (docs/ARCHITECTURE.md names modules relative to the package, so ``rtv3_maniskill/`` counts too)."""
    root = README.parent
    texts = [README, *sorted((root / "docs").glob("*.md")), *sorted((root / "rtv3_maniskill").rglob("*.py"))]
    named = {
        (text.relative_to(root), path)
        for text in texts
        for path in re.findall(r"(?<![\w/.*-])((?:scripts|benchmarks)/[\w/.*-]*\w)", text.read_text())
    }
    assert named, "no script named anywhere"
    missing = sorted(f"{text}: {path}" for text, path in named  # a pattern (scripts/train_*.sh) names >= 1 file
                     if not any(base.glob(path) for base in (root, root / "rtv3_maniskill")))
    assert not missing, "named but missing:\n" + "\n".join(missing)
