"""ROS 2 message definitions in the ``ros2msg`` form MCAP files carry (the form rosbag2 writes).

The complete definition of a type is its own ``.msg`` text followed by that of every type it uses,
recursively, each after a two-line delimiter: a line of 80 ``=`` and ``MSG: <package>/msg/<Type>``.
The ``.msg`` files are read from the ``share/<package>/msg/`` directories of the ament prefixes
(``AMENT_PREFIX_PATH``, then this interpreter's prefix), as rosbag2 does.

``tf2_msgs/msg/TFMessage`` (the standard ``/tf`` type) is known here even where the tf2_msgs
package is not installed: its one-line definition is written out below (the dependencies still come
from geometry_msgs).
"""

from __future__ import annotations

import os
import re
import sys
from collections.abc import Iterable
from pathlib import Path

from redarm_ros.errors import InvalidInputError

SEPARATOR = "=" * 80
PRIMITIVES = frozenset({
    "bool", "byte", "char", "float32", "float64", "int8", "uint8", "int16", "uint16", "int32", "uint32",
    "int64", "uint64", "string", "wstring",
})
# The definition of tf2_msgs/msg/TFMessage (tf2_msgs/msg/TFMessage.msg is this one field).
TF_MESSAGE_TYPE = "tf2_msgs/msg/TFMessage"
BUILTIN_DEFINITIONS = {TF_MESSAGE_TYPE: "geometry_msgs/TransformStamped[] transforms\n"}

_BOUND = re.compile(r"<=\d+$")
_ARRAY = re.compile(r"\[[^\]]*\]$")


def normalize_type(type_name: str) -> str:
    """``pkg/msg/Type`` for ``pkg/msg/Type`` or ``pkg/Type``.

    Raises:
        InvalidInputError: not of either form.
    """
    parts = type_name.strip().split("/")
    if len(parts) == 2 and all(parts):
        return f"{parts[0]}/msg/{parts[1]}"
    if len(parts) == 3 and all(parts) and parts[1] == "msg":
        return type_name.strip()
    raise InvalidInputError(f"not a message type name: {type_name!r} (want pkg/msg/Type)", field="type",
                            value=type_name)


def share_dirs() -> list[Path]:
    """The ``share`` directories searched for ``.msg`` files, in order."""
    prefixes = [p for p in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep) if p]
    prefixes.append(sys.prefix)
    out: list[Path] = []
    for p in prefixes:
        d = Path(p) / "share"
        if d.is_dir() and d not in out:
            out.append(d)
    return out


def msg_file_text(type_name: str, search: Iterable[Path] | None = None) -> str:
    """The ``.msg`` text of ``pkg/msg/Type``.

    Raises:
        InvalidInputError: no ``share/<pkg>/msg/<Type>.msg`` found and no built-in definition.
    """
    full = normalize_type(type_name)
    pkg, _, name = full.split("/")
    for d in share_dirs() if search is None else search:
        f = d / pkg / "msg" / f"{name}.msg"
        if f.is_file():
            return f.read_text(encoding="utf-8")
    if full in BUILTIN_DEFINITIONS:
        return BUILTIN_DEFINITIONS[full]
    raise InvalidInputError(f"no definition found for {full} (looked for share/{pkg}/msg/{name}.msg)",
                            field="type", value=type_name)


def field_types(msg_text: str, package: str) -> list[str]:
    """The non-primitive field types of one ``.msg`` text, as ``pkg/msg/Type``, in order of use."""
    out: list[str] = []
    for raw in msg_text.splitlines():
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        tokens = line.split()
        if len(tokens) < 2 or "=" in tokens[1]:  # a constant (TYPE NAME=value) is always primitive
            continue
        t = _ARRAY.sub("", tokens[0])
        t = _BOUND.sub("", t)
        if t in PRIMITIVES:
            continue
        if t == "Header":  # ROS 1 shorthand, still accepted by the ROS 2 parser
            t = "std_msgs/Header"
        full = normalize_type(t if "/" in t else f"{package}/{t}")
        if full not in out:
            out.append(full)
    return out


def ros2msg_definition(type_name: str, search: Iterable[Path] | None = None) -> str:
    """The complete ``ros2msg`` definition of ``type_name`` (pkg/msg/Type or pkg/Type)."""
    top = normalize_type(type_name)
    dirs = list(share_dirs() if search is None else search)
    texts: dict[str, str] = {}
    order: list[str] = []
    stack = [top]
    while stack:  # depth-first, each type once
        t = stack.pop(0)
        if t in texts:
            continue
        texts[t] = msg_file_text(t, dirs)
        order.append(t)
        deps = [d for d in field_types(texts[t], t.split("/")[0]) if d not in texts]
        stack = deps + stack
    parts = [texts[top].rstrip("\n")]
    for t in order[1:]:
        parts.append(f"{SEPARATOR}\nMSG: {t}\n{texts[t].rstrip(chr(10))}")
    return "\n".join(parts) + "\n"
