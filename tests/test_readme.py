"""The README's Python example runs as written (the real simulator, the shipped checkpoint)."""

from __future__ import annotations

import re
from pathlib import Path

import torch

README = Path(__file__).resolve().parents[1] / "README.md"


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
