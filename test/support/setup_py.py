"""What the package's setup.py declares, read from its source without running it."""

from __future__ import annotations

import ast
from pathlib import Path

SETUP_PY = Path(__file__).resolve().parents[2] / "setup.py"


def console_scripts() -> dict[str, str]:
    """setup.py's console_scripts entry points (name -> "module:function")."""
    tree = ast.parse(SETUP_PY.read_text(encoding="utf-8"))
    for node in ast.walk(tree):
        if isinstance(node, ast.Dict):
            for key, value in zip(node.keys, node.values, strict=True):
                if isinstance(key, ast.Constant) and key.value == "console_scripts":
                    entries = ast.literal_eval(value)
                    return {n.strip(): t.strip() for n, t in (e.split("=", 1) for e in entries)}
    raise AssertionError("setup.py has no console_scripts entry points")
