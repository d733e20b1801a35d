"""The user docs (README.md, docs/*.md): relative links resolve, the size stays bounded, and every
node parameter is in the node reference with its default.

No ROS needed: the node modules' parameter tables are read with ``ast``.
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parent.parent
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
MAX_WORDS = 20_000

# [text](target) and ![alt](target); the target ends at the first blank or closing parenthesis.
LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)\)")
FENCE = re.compile(r"^(```|~~~)")
# Files that another branch adds (the README links them by name); checked once they exist.
PENDING = {"examples"}


def _prose(text: str) -> str:
    """``text`` without fenced code blocks and inline code (links there are not links)."""
    return "\n".join(re.sub(r"`[^`]*`", "", line) for line in _outside_fences(text))


def github_anchor(heading: str) -> str:
    """The anchor GitHub gives a Markdown heading."""
    text = re.sub(r"`", "", heading.strip().lower())
    text = re.sub(r"[^\w\- ]", "", text)
    return text.replace(" ", "-")


def anchors(page: Path) -> set[str]:
    found: set[str] = set()
    seen: dict[str, int] = {}
    for line in _outside_fences(page.read_text(encoding="utf-8")):
        m = re.match(r"^#{1,6}\s+(.*)$", line)
        if m:
            a = github_anchor(m.group(1))
            n = seen.get(a, 0)
            seen[a] = n + 1
            found.add(a if n == 0 else f"{a}-{n}")
        found.update(re.findall(r'<a id="([^"]+)"', line))
    return found


def _outside_fences(text: str) -> list[str]:
    """The lines of ``text`` outside fenced code blocks."""
    out, in_fence = [], False
    for line in text.splitlines():
        if FENCE.match(line.strip()):
            in_fence = not in_fence
            continue
        if not in_fence:
            out.append(line)
    return out


def relative_links(page: Path) -> list[str]:
    return [t for t in LINK.findall(_prose(page.read_text(encoding="utf-8")))
            if not re.match(r"^[a-z][a-z0-9+.-]*:", t)]


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.name)
def test_relative_links_resolve(page: Path) -> None:
    broken = []
    for target in relative_links(page):
        path_part, _, anchor = target.partition("#")
        dest = (page.parent / path_part).resolve() if path_part else page
        rel = dest.relative_to(ROOT) if dest.is_relative_to(ROOT) else dest
        if path_part and not dest.exists():
            if rel.parts and rel.parts[0] in PENDING:
                continue
            broken.append(f"{target}: no file {rel}")
            continue
        if anchor and dest.suffix == ".md" and anchor not in anchors(dest):
            broken.append(f"{target}: no heading for #{anchor} in {rel}")
    assert not broken, f"{page.name}: broken links:\n" + "\n".join(broken)


def test_link_check_catches_a_broken_link(tmp_path: Path) -> None:
    page = tmp_path / "p.md"
    page.write_text("# Title\n[ok](#title) [bad](missing.md) [bad anchor](#nope)\n```\n[code](x.md)\n```\n")
    links = relative_links(page)
    assert links == ["#title", "missing.md", "#nope"]
    assert "title" in anchors(page) and "nope" not in anchors(page)


def test_readme_and_docs_stay_under_the_word_budget() -> None:
    words = sum(len(p.read_text(encoding="utf-8").split()) for p in PAGES)
    assert words <= MAX_WORDS, f"README.md + docs/*.md hold {words} words (budget {MAX_WORDS})"


def _table_params(tree: ast.Module, mapping: str) -> list[tuple[str, object]]:
    """(name, default) of the node parameters built from the parameter table by ``table_params(mapping)``:
    ``mapping`` is the module's dict of ROS name -> (table section, name there)."""
    from redarm_ros.param_table import table

    for node in tree.body:
        if isinstance(node, ast.AnnAssign | ast.Assign):
            targets = [node.target] if isinstance(node, ast.AnnAssign) else node.targets
            if any(getattr(t, "id", "") == mapping for t in targets):
                names = ast.literal_eval(node.value)  # type: ignore[arg-type]
                return [(ros, table()[section].param(name).default) for ros, (section, name) in names.items()]
    raise AssertionError(f"no {mapping} in the module")


def _node_params(module: Path) -> list[tuple[str, object]]:
    """(name, default) of every ParamSpec in the module's PARAMS list, and of the shared specs."""
    shared = {"NICE_PARAM": ("nice", -10), "PROCESS_RT_PARAM": ("realtime_priority", 20)}
    tree = ast.parse(module.read_text(encoding="utf-8"))
    for node in tree.body:
        if isinstance(node, ast.Assign) and any(getattr(t, "id", "") == "PARAMS" for t in node.targets):
            out = []
            for item in node.value.elts:  # type: ignore[attr-defined]
                if isinstance(item, ast.Starred) and getattr(item.value.func, "id", "") == "table_params":
                    out += _table_params(tree, getattr(item.value.args[0], "id", ""))
                    continue
                if isinstance(item, ast.Starred):  # *urdf_arm_params(...): the URDF arm's three strings
                    assert getattr(item.value.func, "id", "") == "urdf_arm_params", ast.dump(item)
                    out += [("urdf", ""), ("base_link", ""), ("tip_link", "")]
                    continue
                if isinstance(item, ast.Name):
                    out.append(shared[item.id])
                    continue
                name = ast.literal_eval(item.args[0])
                try:
                    default = ast.literal_eval(item.args[1])
                except ValueError:
                    default = None  # a named constant or a type: the name is checked only
                out.append((name, default))
            return out
    raise AssertionError(f"no PARAMS in {module}")


def _section(text: str, heading: str) -> str:
    m = re.search(rf"^## {re.escape(heading)}\n(.*?)(?=^## |\Z)", text, re.S | re.M)
    assert m, f"docs/nodes.md has no section '## {heading}'"
    return m.group(1)


def _same(doc: str, code: object) -> bool:
    """Whether the default written in the docs (YAML syntax) is the code's default."""
    value = yaml.safe_load(doc)
    if isinstance(code, bool) or isinstance(value, bool):
        return value is code
    if isinstance(code, (int, float)) and isinstance(value, (int, float)):
        return float(value) == float(code)
    return value == code


@pytest.mark.parametrize("node", ["ik_service", "controller", "can_driver", "description", "view"])
def test_every_node_parameter_is_in_the_reference(node: str) -> None:
    text = _section((ROOT / "docs" / "nodes.md").read_text(encoding="utf-8"), node)
    rows = {}
    for line in text.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) >= 3:
            names = re.findall(r"`([^`]+)`", cells[0])
            defaults = re.findall(r"`([^`]*)`", cells[2] if node == "view" else cells[1])
            for i, name in enumerate(names):
                rows[name] = defaults[i] if i < len(defaults) else (defaults[0] if defaults else "")
    missing, wrong = [], []
    for name, default in _node_params(ROOT / "redarm_ros" / "nodes" / f"{node}.py"):
        if name not in rows:
            missing.append(name)
        elif default is not None and not _same(rows[name], default):
            wrong.append(f"{name}: docs {rows[name]!r}, code {default!r}")
    assert not missing, f"parameters of {node} missing from docs/nodes.md: {missing}"
    assert not wrong, f"defaults of {node} differ: {wrong}"
