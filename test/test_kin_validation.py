"""Input validation of every public IK entry: typed errors that say what is wrong, never a raw numpy
error, never a malformed row flagged valid; unknown keyword arguments are refused."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest

from redarm_ros.errors import InvalidInputError
from redarm_ros.kinematics import IKStatus, load_arm

ARM = load_arm("pa10")
Q0 = np.array([0.3, 0.6, -0.4, 1.2, 0.5, -0.7, 0.9])
T0 = ARM.fk(Q0)


def _bad_poses() -> dict[str, tuple[Any, str]]:
    """name -> (pose, a word the message must contain)."""
    nan = T0.copy()
    nan[1, 3] = math.nan
    inf = T0.copy()
    inf[0, 0] = math.inf
    huge = T0.copy()
    huge[0, 3] = 1e308
    zero_r = T0.copy()
    zero_r[:3, :3] = 0.0
    mirror = T0.copy()
    mirror[:3, 0] *= -1.0
    bottom = T0.copy()
    bottom[3, 0] = 0.5
    return {
        "nan": (nan, "NaN"),
        "inf": (inf, "inf"),
        "1e308 position": (huge, "out of range"),
        "zero rotation": (zero_r, "orthonormal"),
        "det -1": (mirror, "det"),
        "bottom row": (bottom, "bottom row"),
        "ragged": ([[1.0, 0.0, 0.0, 0.0], [0.0, 1.0]], "ragged"),
        "complex": (T0.astype(complex), "complex"),
        "string": ("T", "numeric"),
        "3x4": (T0[:3], "shape"),
    }


BAD_POSES = _bad_poses()


@pytest.mark.parametrize("case", sorted(BAD_POSES))
def test_every_entry_refuses_a_bad_pose_with_the_reason(case: str) -> None:
    T, word = BAD_POSES[case]
    for call in (
        lambda: ARM.ik(T, 0.1),
        lambda: ARM.ik_u(T, [1.0, 0.0, 0.0]),
        lambda: ARM.feasible_swivels(T),
        lambda: ARM.elbow_circle(T),
        lambda: ARM.ik_batch(np.array([T0, T]) if case not in ("ragged", "string", "3x4") else T, 0.0),
        lambda: ARM.ik_nearest_batch(np.array([T0, T]) if case not in ("ragged", "string", "3x4") else T, Q0),
    ):
        with pytest.raises(InvalidInputError) as err:
            call()
        assert word.lower() in str(err.value).lower(), (case, str(err.value))
    q, info = ARM.ik_nearest(T, Q0)
    assert q is None and info.status is IKStatus.INVALID_INPUT and word.lower() in info.message.lower()


def test_batch_names_the_bad_row_and_never_flags_it_valid() -> None:
    Ts = np.repeat(T0[None], 5, axis=0)
    Ts[3, :3, :3] = 0.0  # R = 0: once accepted and flagged valid
    with pytest.raises(InvalidInputError) as err:
        ARM.ik_batch(Ts, 0.0)
    assert "Ts[3]" in str(err.value) and err.value.value == [3]
    Ts[1, :3, :3] *= 1.01  # a second bad row
    with pytest.raises(InvalidInputError) as err:
        ARM.ik_batch(Ts, 0.0)
    assert "Ts[1]" in str(err.value) and "1 more" in str(err.value) and err.value.value == [1, 3]


#: The entries that take one scalar or small-vector argument besides a good pose, fed the bad value.
ENTRIES = {
    "ik swivel": lambda v: ARM.ik(T0, v),
    "ik_batch swivels": lambda v: ARM.ik_batch(np.array([T0, T0]), v),
    "ik_u quaternion": lambda v: ARM.ik_u(T0, v),
}
#: (entry, bad value, a word the message must contain)
BAD_ARGUMENTS = [
    ("ik swivel", math.nan, "NaN"),
    ("ik swivel", math.inf, "finite"),
    ("ik swivel", 1e308, "out of range"),
    ("ik swivel", 1 + 2j, "real"),
    ("ik swivel", "x", "number"),
    ("ik swivel", True, "real"),
    ("ik swivel", [0.1, 0.2], "number"),
    ("ik_batch swivels", [0.1, math.nan], "NaN"),
    ("ik_batch swivels", [0.1, 1e300], "out of range"),
    ("ik_batch swivels", [0.1, 0.2, 0.3], "shape"),
    ("ik_batch swivels", [[0.1], [0.2, 0.3]], "ragged"),
    ("ik_batch swivels", np.array([0.1, 0.2j]), "complex"),
    ("ik_u quaternion", [1.0, 0.0, 0.5], "unit"),
    ("ik_u quaternion", [2.0, 0.0, 0.0], "unit"),
    ("ik_u quaternion", [1.0, 0.0], "shape"),
    ("ik_u quaternion", [math.nan, 0, 0], "NaN"),
    ("ik_u quaternion", [1j, 0, 0], "complex"),
]


@pytest.mark.parametrize("entry, value, word", BAD_ARGUMENTS)
def test_a_bad_swivel_argument_is_refused_with_the_reason(entry: str, value: Any, word: str) -> None:
    with pytest.raises(InvalidInputError) as err:
        ENTRIES[entry](value)
    assert word in str(err.value)


@pytest.mark.parametrize(
    "q, word",
    [
        (np.full(7, math.nan), "NaN"),
        (np.full(7, math.inf), "inf"),
        (np.full(7, 1e308), "out of range"),
        (np.zeros(6), "7 joints"),
        ([[0.0] * 7, [0.0]], "ragged"),
        (np.zeros(7, complex), "complex"),
        ("q", "numeric"),
    ],
)
def test_bad_joint_vectors(q: Any, word: str) -> None:
    for call in (lambda: ARM.swivel(q), lambda: ARM.fk(q), lambda: ARM.swivel_u(q)):
        with pytest.raises(InvalidInputError) as err:
            call()
        assert word in str(err.value)
    qq, info = ARM.ik_nearest(T0, q)
    assert qq is None and info.status is IKStatus.INVALID_INPUT and word in info.message


def test_nearest_options() -> None:
    for bad, word in (([1, 2], "shape"), ([-1.0] * 7, ">= 0"), ([math.nan] * 7, "NaN")):
        q, info = ARM.ik_nearest(T0, Q0, weights=bad)
        assert q is None and info.status is IKStatus.INVALID_INPUT and word in info.message
    for bad, word in ((-1.0, ">= 0"), (math.nan, "NaN"), ("soon", "number")):
        q, info = ARM.ik_nearest(T0, Q0, timeout_s=bad)
        assert q is None and info.status is IKStatus.INVALID_INPUT and word in info.message
    with pytest.raises(InvalidInputError):
        ARM.ik_nearest_batch(np.array([T0]), np.zeros((2, 7)))


@pytest.mark.parametrize("arm_name", ["pa10", "powercube6"])
def test_unknown_keyword_arguments_are_refused(arm_name: str) -> None:
    arm = load_arm(arm_name)
    T = arm.fk(np.full(arm.n, 0.2))
    seed = np.zeros(arm.n)
    with pytest.raises(TypeError, match="fine_samples"):
        arm.ik_nearest(T, seed, fine_samples=0)  # type: ignore[call-arg]
    with pytest.raises(TypeError, match="wieghts"):
        arm.ik_nearest(T, seed, wieghts=np.ones(arm.n))  # type: ignore[call-arg]
    with pytest.raises(TypeError):
        arm.ik(T, 0.0, all_copy=True)  # type: ignore[call-arg]


def test_generic_chain_and_numeric_solvers_refuse_unknown_options(tmp_path: Any) -> None:
    from redarm_ros.kinematics.numeric import solve_dls, solve_flow

    with pytest.raises(TypeError):
        solve_dls(ARM, T0, Q0, samples=3)  # type: ignore[call-arg]
    with pytest.raises(TypeError):
        solve_flow(ARM, T0, Q0, refine=3)  # type: ignore[call-arg]


def test_load_arm_override_errors_name_the_key() -> None:
    from redarm_ros.errors import ConfigError

    with pytest.raises(ConfigError, match="no_such_key"):
        load_arm("pa10", no_such_key=1)
