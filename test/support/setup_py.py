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


def _constants(tree: ast.Module) -> dict[str, str]:
    """Module-level string constants of setup.py (``PACKAGE = "redarm_ros"``)."""
    out = {}
    for node in tree.body:
        if isinstance(node, ast.Assign) and isinstance(node.value, ast.Constant) and \
                isinstance(node.value.value, str):
            out.update({t.id: node.value.value for t in node.targets if isinstance(t, ast.Name)})
    return out


def _text(node: ast.expr, names: dict[str, str]) -> str:
    """A string literal or an f-string over setup.py's constants."""
    if isinstance(node, ast.Constant) and isinstance(node.value, str):
        return node.value
    if isinstance(node, ast.JoinedStr):
        return "".join(_text(v.value if isinstance(v, ast.FormattedValue) else v, names) for v in node.values)
    if isinstance(node, ast.Name) and node.id in names:
        return names[node.id]
    raise AssertionError(f"setup.py: cannot read {ast.dump(node)} as text")


def package_data() -> dict[str, list[str]]:
    """setup.py's package_data (package -> file patterns), f-strings over its constants resolved."""
    tree = ast.parse(SETUP_PY.read_text(encoding="utf-8"))
    names = _constants(tree)
    for node in ast.walk(tree):
        if isinstance(node, ast.keyword) and node.arg == "package_data" and isinstance(node.value, ast.Dict):
            return {_text(k, names): [_text(e, names) for e in v.elts]  # type: ignore[attr-defined]
                    for k, v in zip(node.value.keys, node.value.values, strict=True)}
    raise AssertionError("setup.py declares no package_data")
