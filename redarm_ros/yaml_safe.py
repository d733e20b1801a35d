"""YAML for the whole package: ``yaml.safe_load`` with libyaml's C parser when PyYAML has it.

The schema (SafeLoader's constructors and resolvers) is the same either way; the C parser only reads
faster, about 6x, which matters because every process of the stack reads the parameter table and its
arm files at start, and the tests start hundreds of them. Errors are ``yaml.YAMLError`` with a
``problem_mark`` (line, column) from both parsers.
"""

from __future__ import annotations

from typing import IO, Any

import yaml

SafeLoader: type = getattr(yaml, "CSafeLoader", yaml.SafeLoader)


def safe_load(stream: str | bytes | IO[str] | IO[bytes]) -> Any:
    """Parse one YAML document with the safe schema (as ``yaml.safe_load``)."""
    return yaml.load(stream, Loader=SafeLoader)  # noqa: S506 (a safe loader)
