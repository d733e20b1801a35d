"""The controller's parameter table (redarm_ros/parameters.yaml) and the classes built from it: defaults
construct, every bound refuses bad values with the section's error naming the field (parametrised from
the table, so a new parameter is covered without a new test), table and classes agree, from_dict
refuses unknown keys at every depth, and the table ships as package data."""

from __future__ import annotations

import dataclasses
import importlib
import math
import pickle
from importlib import resources

import pytest
from support.setup_py import package_data

import redarm_ros.control.params  # noqa: F401  (builds every class of the table)
from redarm_ros.control.params import ControllerParams
from redarm_ros.errors import ConfigError, InvalidInputError
from redarm_ros.param_table import (
    BOUND_WORDS,
    TABLE_FILE,
    group_class,
    load_table,
    table,
)

#: Where each class of the table has always been imported from.
HOMES = {
    "heading": ("redarm_ros.control.attractor", "HeadingParams"),
    "speed": ("redarm_ros.control.attractor", "SpeedParams"),
    "swivel": ("redarm_ros.control.swivel_dynamics", "SwivelParams"),
    "paper_swivel": ("redarm_ros.control.paper_redundancy", "PaperSwivelParams"),
    "capsules": ("redarm_ros.geometry.obstacles", "ArmCapsules"),
    "stream": ("redarm_ros.control.params", "StreamParams"),
    "servo": ("redarm_ros.control.params", "ServoParams"),
    "replan": ("redarm_ros.control.params", "ReplanParams"),
    "controller": ("redarm_ros.control.params", "ControllerParams"),
}

NAN, INF = math.nan, math.inf

#: Values each bound word must refuse (argument-taking words: built from the argument below).
BAD = {
    "positive": [0.0, -1.0, NAN, INF, "1", None],
    "nonnegative": [-1e-9, NAN, INF, "0", None],
    "finite": [NAN, -INF, "0", None],
    "unit_interval": [-0.1, 1.1, NAN, None],
    "share": [0.0, 1.5, NAN, None],
    "bool": [1, "yes", None],
    "integer": [1.0, True, "7", None],
    "int_positive": [0, -3, 1.0, True, None],
    "int_nonnegative": [-1, 2.0, None],
    "angles3": [(0.1, 0.2), (0.1, 0.2, 0.3, 0.4), (0.0, NAN, 0.0), "abc", None],
    "lengths4": [(0.1, 0.1, 0.1), (0.1, -0.1, 0.1, 0.1), (0.1, INF, 0.1, 0.1), None],
    "links": [(4,), (-1,), (1.0,), (True,), None],
}

#: Edge values each bound word must accept.
GOOD = {
    "positive": [1e-12, 3, 1e9], "nonnegative": [0.0, 0, 2.5], "finite": [-1e9, 0.0, 1e9],
    "unit_interval": [0.0, 1.0, 0.5], "share": [1e-12, 1.0], "bool": [True, False],
    "integer": [-5, 0, 7], "int_positive": [1, 1000], "int_nonnegative": [0, 3],
    "angles3": [(0.0, 0.3, -1.0), [1, 2, 3]], "lengths4": [(0.0, 0.0, 0.0, 0.0), [0.1, 0.2, 0.3, 0.4]],
    "links": [(), (0, 1, 2, 3), [3]],
}


def _bad_values(bound) -> list:
    if bound.word == "int_at_least":
        return [bound.arg - 1, float(bound.arg), True, None]
    if bound.word == "choice":
        return ["not-" + bound.arg[0], bound.arg[0].upper(), None]
    if bound.word == "range":
        lo, hi = bound.arg
        return [lo - 1e-9, hi + 1e-9, NAN, 1e300, "0", None]
    return BAD[bound.word]


def _good_values(bound) -> list:
    if bound.word == "int_at_least":
        return [bound.arg, bound.arg + 1]
    if bound.word == "choice":
        return list(bound.arg)
    if bound.word == "range":
        return [bound.arg[0], bound.arg[1], 0.5 * (bound.arg[0] + bound.arg[1])]
    return GOOD[bound.word]


def _rows(values):
    return [pytest.param(section, p.name, v, id=f"{section}.{p.name}={v!r}")
            for section, g in table().items() for p in g.params if p.group is None
            for v in values(p.bound)]


def _valid(section: str, name: str, value) -> dict:
    # unfold_pitch asks for a bent elbow besides its bound (3 finite angles)
    if (section, name) == ("controller", "unfold_pitch") and abs(float(list(value)[1])) < 0.2:
        value = (value[0], 0.5, value[2])
    return {name: value}


def test_every_bound_word_used_has_test_values() -> None:
    used = {p.bound.word for g in table().values() for p in g.params}
    assert used <= set(BOUND_WORDS)
    missing = used - set(BAD) - {"int_at_least", "range", "choice", "group"}
    assert not missing, f"add bad and good values for bound(s) {missing} to this test"


@pytest.mark.parametrize("section", list(table()))
def test_every_group_constructs_with_its_defaults(section: str) -> None:
    cls = group_class(section)
    made = cls()
    for p in table()[section].params:
        value = getattr(made, p.name)
        if p.group is None:
            assert value == p.default and type(value) is type(p.default), p.name
        else:
            assert isinstance(value, group_class(p.group)) and value == group_class(p.group)(), p.name


@pytest.mark.parametrize(("section", "name", "bad"), _rows(_bad_values))
def test_every_bound_refuses_a_bad_value(section: str, name: str, bad) -> None:
    group = table()[section]
    with pytest.raises(InvalidInputError) as caught:
        group_class(section)(**{name: bad})
    exc = caught.value
    assert type(exc) is group.error
    assert exc.field == name and (exc.value is bad or exc.value == bad)
    message = str(exc)
    assert f"{group.class_name}.{name} must be {group.param(name).bound.phrase}" in message
    assert repr(bad) in message


@pytest.mark.parametrize(("section", "name", "good"), _rows(_good_values))
def test_every_bound_accepts_its_edge_values(section: str, name: str, good) -> None:
    given = _valid(section, name, good)[name]  # (unfold_pitch: the edge value with a bent elbow)
    made = group_class(section)(**{name: given})
    stored = getattr(made, name)
    assert stored == (tuple(given) if isinstance(given, (list, tuple)) else given)
    assert not isinstance(stored, list)  # sequences are stored as tuples (hashable, frozen)


def test_unfold_pitch_needs_a_bent_elbow() -> None:
    with pytest.raises(ConfigError, match="elbow pitch of at least 0.2") as caught:
        ControllerParams(unfold_pitch=(0.4, 0.1, 1.0))
    assert caught.value.field == "unfold_pitch"
    assert ControllerParams(unfold_pitch=[0.4, -0.2, 1]).unfold_pitch == (0.4, -0.2, 1.0)


def test_table_and_classes_agree() -> None:
    assert set(table()) == set(HOMES), "every section has a home module (and every class a section)"
    for section, (module, name) in HOMES.items():
        cls = getattr(importlib.import_module(module), name)
        group = table()[section]
        assert cls is group_class(section) and cls.__name__ == group.class_name
        assert cls.__module__ == module
        assert dataclasses.is_dataclass(cls) and cls.__dataclass_params__.frozen
        fields = dataclasses.fields(cls)
        assert [f.name for f in fields] == [p.name for p in group.params]
        for f, p in zip(fields, group.params, strict=True):
            assert f.type == (group_class(p.group) if p.group else p.bound.type), p.name
            assert f"``{p.name}``" in cls.__doc__  # help() explains every field
            if p.unit:
                assert f"``{p.name}`` [{p.unit}]" in cls.__doc__


def test_float_defaults_are_floats() -> None:
    for g in table().values():
        for p in g.params:
            if p.bound.type is float:
                assert isinstance(p.default, float), f"{g.section}.{p.name}"


def test_built_classes_behave_as_frozen_dataclasses() -> None:
    p = ControllerParams.from_dict({"speed": {"v_max": 0.25}, "unfold_pitch": [0.4, 1.0, 1.0]})
    assert pickle.loads(pickle.dumps(p)) == p and hash(pickle.loads(pickle.dumps(p))) == hash(p)
    assert dataclasses.replace(p, dt=0.02).dt == 0.02 and p.with_(dt=0.02) == dataclasses.replace(p, dt=0.02)
    with pytest.raises(dataclasses.FrozenInstanceError):
        p.dt = 0.02  # type: ignore[misc]
    with pytest.raises(ConfigError):
        dataclasses.replace(p, dt=-1.0)  # replace validates too


def test_from_dict_refuses_unknown_keys_at_every_depth() -> None:
    with pytest.raises(ConfigError, match=r"unknown controller parameter\(s\) \['prefered_swivel'\]") as top:
        ControllerParams.from_dict({"prefered_swivel": 0.3})
    assert top.value.field == "prefered_swivel" and "known: " in str(top.value)
    with pytest.raises(ConfigError, match=r"unknown replan parameter\(s\) \['vais'\]") as nested:
        ControllerParams.from_dict({"replan": {"vias": 10, "vais": 10}})
    assert nested.value.field == "replan.vais" and "'vias'" in str(nested.value)
    with pytest.raises(ConfigError, match="heading must be a mapping") as not_mapping:
        ControllerParams.from_dict({"heading": 3.0})
    assert not_mapping.value.field == "heading"
    with pytest.raises(ConfigError, match="must be a mapping"):
        ControllerParams.from_dict([("dt", 0.01)])  # type: ignore[arg-type]


def test_from_dict_names_the_path_of_a_bad_nested_value() -> None:
    with pytest.raises(ConfigError, match=r"SpeedParams.v_max must be finite and > 0") as caught:
        ControllerParams.from_dict({"speed": {"v_max": -1.0}})
    assert caught.value.field == "speed.v_max" and caught.value.value == -1.0


def test_from_dict_reads_every_group_from_the_table() -> None:
    full = {p.name: ({} if p.group else p.default) for p in table()["controller"].params}
    assert ControllerParams.from_dict(full) == ControllerParams()
    p = ControllerParams.from_dict({"capsules": {"radii": [0.1, 0.07, 0.06, 0.04], "table_links": [2, 3]},
                                    "paper_swivel": {"samples": 12}})
    assert p.capsules.radii == (0.1, 0.07, 0.06, 0.04) and p.capsules.table_links == (2, 3)
    assert p.paper_swivel.samples == 12


@pytest.mark.parametrize(("text", "complaint"), [
    ("a: {class: A, params: {x: {default: 1.0, unit: m, bound: tiny, doc: d}}}", "unknown bound"),
    ("a: {class: A, params: {x: {default: 1, unit: m, bound: positive, doc: d}}}", "with a dot"),
    ("a: {class: A, params: {x: {default: 1e-6, unit: m, bound: positive, doc: d}}}", "with a dot"),
    ("a: {class: A, params: {x: {default: 1.0, unit: m, bound: positive}}}", "exactly the keys"),
    ("a: {class: A, params: {x: {default: -1.0, unit: m, bound: positive, doc: d}}}", "is not finite"),
    ("a: {class: A, params: {x: {bound: {group: b}, doc: d}}}", "unknown section 'b'"),
    ("a: {class: A, error: OopsError, params: {}}", "error must be one of"),
    ("a: {params: {}}", "needs class and params"),
])
def test_malformed_tables_are_refused(text: str, complaint: str) -> None:
    with pytest.raises(ConfigError, match=complaint):
        load_table(text)


def test_table_is_installed_as_package_data() -> None:
    assert TABLE_FILE in package_data().get("redarm_ros", []), \
        "setup.py's package_data must list the table, or an installed (non-editable) package lacks it"
    assert resources.files("redarm_ros").joinpath(TABLE_FILE).is_file()


def test_controller_node_defaults_and_choices_are_the_tables() -> None:
    pytest.importorskip("rclpy")
    node = pytest.importorskip("redarm_ros.nodes.controller")
    specs = {s.name: s for s in node.PARAMS}
    for node_name, (section, name) in node.NODE_TO_TABLE.items():
        row = table()[section].param(name)
        spec = specs[node_name]
        assert spec.default == row.default and type(spec.default) is type(row.default), node_name
        if row.bound.word == "choice":
            assert all(spec.validate(c) is None for c in row.bound.arg), node_name
            assert spec.validate("not-" + row.bound.arg[0]) is not None, node_name


def test_controller_node_declares_its_core_parameters_from_the_table() -> None:
    """One place per parameter: a node parameter of NODE_TO_TABLE takes its default, type, bound (as the
    validator and the descriptor's range) and description from the table row; the node's source writes
    none of them."""
    pytest.importorskip("rclpy")
    node = pytest.importorskip("redarm_ros.nodes.controller")
    specs = {s.name: s for s in node.PARAMS}
    with open(node.__file__, encoding="utf-8") as f:
        text = f.read()
    for ros_name, (section, name) in node.NODE_TO_TABLE.items():
        row = table()[section].param(name)
        spec = specs[ros_name]
        assert f'ParamSpec("{ros_name}"' not in text, ros_name
        assert " ".join(row.doc.split())[1:] in spec.description, ros_name
        assert spec.range == (row.bound.arg if row.bound.word == "range" else None), ros_name
        assert all(spec.validate(v) is not None for v in _bad_values(row.bound)), ros_name
        assert all(spec.validate(v) is None for v in _good_values(row.bound)), ros_name
