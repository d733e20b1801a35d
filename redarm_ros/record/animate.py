"""Pictures of a run from its recording: PNG frames and an animated GIF of the simulated arm.

* :class:`SceneRenderer` draws the arm at given joint angles in a scene (table, obstacles) with the
  current goal as a marker (green sphere plus a stick along the goal's tool z axis; red when the
  controller rejected it) and a caption, headless with pybullet's TinyRenderer in a pybullet client
  of its own (the same renderer and URDF as the simulator's snapshots). No ROS here.
* :func:`load_timeline` reads ``/joint_states``, ``/goal_pose`` and ``/controller/state`` back from an
  MCAP recording; :func:`frames` samples it at a fixed rate, shortening stretches where nothing moves;
  :func:`write_gif` writes the frames with imageio, all quantized to one shared palette, so the GIF
  stores only what changes between frames.
* :func:`write_png` writes one picture (Pillow) atomically, for the simulator's and the demo's snapshots.

Units: m, rad, ns for recording times, s for durations.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

GOAL_OK_RGBA = (0.1, 0.8, 0.2, 1.0)
GOAL_BAD_RGBA = (0.9, 0.1, 0.1, 1.0)
# Camera of the demo pictures: closer than the simulator's default, the arm and the demo goals in view.
DEMO_CAMERA: dict[str, Any] = {"target": (0.3, 0.0, 0.55), "distance": 2.25, "yaw": 40.0, "pitch": -18.0}


@dataclass
class Timeline:
    """A run as recorded: joint samples, goals and controller phases (times in ns)."""

    joint_names: list[str]
    t: np.ndarray  # (k,) ns
    q: np.ndarray  # (k, n) rad, columns in joint_names order
    goals: list[tuple[int, np.ndarray, np.ndarray]] = field(default_factory=list)  # (t, pos, quat xyzw)
    phases: list[tuple[int, str, str]] = field(default_factory=list)  # (t, phase, message)

    def goal_at(self, t: int) -> tuple[int, np.ndarray, np.ndarray] | None:
        """The latest goal sent at or before ``t`` (with its index in ``goals``), or None."""
        i = _last_index([g[0] for g in self.goals], t)
        return None if i < 0 else (i, self.goals[i][1], self.goals[i][2])

    def phase_at(self, t: int) -> tuple[str, str]:
        """The controller's (phase, message) at ``t`` ('' before the first state)."""
        i = _last_index([p[0] for p in self.phases], t)
        return ("", "") if i < 0 else self.phases[i][1:]

    def q_at(self, t: int) -> np.ndarray:
        """Joint angles of the latest sample at or before ``t`` (the first sample before that)."""
        i = int(np.searchsorted(self.t, t, side="right")) - 1
        return self.q[max(i, 0)]

    def tool_path(self, arm: Any, step: int = 1) -> np.ndarray:
        """(m, 3) tool positions (m) of every ``step``-th sample, by the arm model's forward kinematics."""
        return np.array([arm.fk(q)[:3, 3] for q in self.q[::step]])


def _last_index(times: Sequence[int], t: int) -> int:
    return int(np.searchsorted(np.asarray(times, dtype=np.int64), t, side="right")) - 1


def load_timeline(path: str | Path, joint_names: Sequence[str]) -> Timeline:
    """Read ``/joint_states``, ``/goal_pose`` and ``/controller/state`` from an MCAP recording.

    Raises:
        ValueError: the recording has no ``/joint_states`` with all of ``joint_names``.
    """
    from redarm_ros.record.mcap_io import read_messages

    names = list(joint_names)
    ts: list[int] = []
    qs: list[list[float]] = []
    goals: list[tuple[int, np.ndarray, np.ndarray]] = []
    phases: list[tuple[int, str, str]] = []
    for topic, t, msg in read_messages(path, ["/joint_states", "/goal_pose", "/controller/state"]):
        if topic == "/joint_states":
            pos = dict(zip(msg.name, msg.position, strict=False))
            if all(n in pos for n in names):
                ts.append(t)
                qs.append([pos[n] for n in names])
        elif topic == "/goal_pose":
            p, o = msg.pose.position, msg.pose.orientation
            goals.append((t, np.array([p.x, p.y, p.z]), np.array([o.x, o.y, o.z, o.w])))
        else:
            phases.append((t, msg.phase, msg.message))
    if not ts:
        raise ValueError(f"{path}: no /joint_states with the joints {names}")
    return Timeline(names, np.asarray(ts, dtype=np.int64), np.asarray(qs, dtype=float), goals, phases)


class SceneRenderer:
    """The arm (``arm``: a kinematics model) in ``scene`` (dict: ``table_height``, ``obstacles``),
    rendered at ``size`` (width, height) px from ``camera`` (see ``PybulletPlant.render``)."""

    def __init__(self, arm: Any, scene: dict[str, Any] | None = None, size: tuple[int, int] = (640, 480),
                 camera: dict[str, Any] | None = None) -> None:
        from redarm_ros.sim.plant import PybulletPlant

        self.size = (int(size[0]), int(size[1]))
        self.camera = dict(camera or {})
        self.plant = PybulletPlant.create(arm)
        if scene:
            self.plant.add_scene(scene)
        pb, cid = self.plant.pb, self.plant.cid
        self._goal_bodies: dict[bool, tuple[int, int]] = {}
        for ok, rgba in ((True, GOAL_OK_RGBA), (False, GOAL_BAD_RGBA)):
            ball = pb.createVisualShape(pb.GEOM_SPHERE, radius=0.03, rgbaColor=list(rgba),
                                        physicsClientId=cid)
            stick = pb.createVisualShape(pb.GEOM_CYLINDER, radius=0.008, length=0.12, rgbaColor=list(rgba),
                                         visualFramePosition=[0, 0, -0.06], physicsClientId=cid)
            self._goal_bodies[ok] = tuple(  # type: ignore[assignment]
                pb.createMultiBody(0.0, -1, v, [0, 0, -10], physicsClientId=cid) for v in (ball, stick))

    def render(self, q: Sequence[float], goal: tuple[np.ndarray, np.ndarray] | None = None, *,
               goal_ok: bool = True, caption: str = "") -> np.ndarray:
        """RGB image (h, w, 3) uint8 of the arm at ``q`` (rad) with ``goal`` (position, quat xyzw)."""
        pb, cid = self.plant.pb, self.plant.cid
        self.plant.reset_joints(q)
        for ok, bodies in self._goal_bodies.items():
            show = goal is not None and ok == goal_ok
            pos = [float(v) for v in goal[0]] if show and goal is not None else [0.0, 0.0, -10.0]
            orn = [float(v) for v in goal[1]] if show and goal is not None else [0.0, 0.0, 0.0, 1.0]
            for b in bodies:
                pb.resetBasePositionAndOrientation(b, pos, orn, physicsClientId=cid)
        img = self.plant.render(*self.size, **self.camera)
        return draw_caption(img, caption) if caption else img

    def swatch(self) -> np.ndarray:
        """A picture with both goal markers (ok and rejected) in view and a caption band: a palette
        sample holding every colour the frames can show."""
        target = np.asarray(self.camera.get("target", (0.2, 0.0, 0.5)), dtype=float)
        pb, cid = self.plant.pb, self.plant.cid
        for dx, bodies in ((-0.08, self._goal_bodies[True]), (0.08, self._goal_bodies[False])):
            for b in bodies:
                pb.resetBasePositionAndOrientation(b, (target + [dx, -0.1, 0.0]).tolist(), [0, 0, 0, 1],
                                                   physicsClientId=cid)
        img = draw_caption(self.plant.render(*self.size, **self.camera), "goal 0/0 swatch: reaching")
        for bodies in self._goal_bodies.values():
            for b in bodies:
                pb.resetBasePositionAndOrientation(b, [0, 0, -10], [0, 0, 0, 1], physicsClientId=cid)
        return img

    def close(self) -> None:
        """Disconnect the renderer's pybullet client."""
        self.plant.close()


def draw_caption(img: np.ndarray, text: str) -> np.ndarray:
    """``img`` with ``text`` in a light band along the top (Pillow; a copy)."""
    from PIL import Image, ImageDraw, ImageFont

    im = Image.fromarray(img)
    draw = ImageDraw.Draw(im)
    size = max(12, img.shape[0] // 30)
    try:
        font: Any = ImageFont.load_default(size=size)
    except TypeError:  # Pillow before 10.1: one bitmap size only
        font = ImageFont.load_default()
    draw.rectangle([0, 0, img.shape[1], size + 10], fill=(245, 245, 245))
    draw.text((8, 4), text, fill=(20, 20, 20), font=font)
    return np.asarray(im)


def frames(timeline: Timeline, renderer: SceneRenderer, *, fps: float = 10.0,
           caption: Callable[[int, Timeline], str] | None = None, hold_s: float = 0.6,
           still_rad: float = 2e-4, start_ns: int | None = None, end_ns: int | None = None
           ) -> Iterator[np.ndarray]:
    """Render ``timeline`` at ``fps`` frames per second of recording time.

    Where the arm stands still (no joint moved by more than ``still_rad`` since the last frame) and
    the goal and caption are unchanged, only ``hold_s`` seconds of frames are kept: the GIF shows
    the motion, not the waiting.
    """
    t0 = int(timeline.t[0] if start_ns is None else start_ns)
    t1 = int(timeline.t[-1] if end_ns is None else end_ns)
    step = int(1e9 / fps)
    last_q: np.ndarray | None = None
    last_key: tuple[Any, ...] = ()
    still = 0
    for t in range(t0, t1 + 1, step):
        q = timeline.q_at(t)
        g = timeline.goal_at(t)
        phase, _msg = timeline.phase_at(t)
        text = caption(t, timeline) if caption is not None else ""
        key = (None if g is None else g[0], phase, text)
        moved = last_q is None or float(np.max(np.abs(q - last_q))) > still_rad
        if not moved and key == last_key:
            still += 1
            if still > hold_s * fps:
                continue
        else:
            still = 0
        last_q, last_key = q, key
        goal = None if g is None else (g[1], g[2])
        yield renderer.render(q, goal, goal_ok=phase != "rejected", caption=text)


def write_png(path: str | os.PathLike[str], image: np.ndarray) -> str:
    """Write an (h, w, 3) RGB or (h, w, 4) RGBA uint8 ``image`` as PNG to ``path``; returns the path.

    Atomic (temp file + rename): a reader polling for the file never sees half of it.
    """
    from PIL import Image

    img = np.asarray(image)
    if img.dtype != np.uint8 or img.ndim != 3 or img.shape[2] not in (3, 4) or 0 in img.shape[:2]:
        raise ValueError(f"expected an (h, w, 3|4) uint8 image, got {img.dtype} {img.shape}")
    path = os.fspath(path)
    tmp = f"{path}.tmp{os.getpid()}"
    Image.fromarray(img).save(tmp, format="PNG")
    os.replace(tmp, path)
    return path


def shared_palette(sample: Sequence[np.ndarray], colors: int = 256) -> Any:
    """One adaptive palette (a Pillow 'P' image) for all frames, from a few sample frames."""
    from PIL import Image

    strip = np.concatenate([np.asarray(s) for s in sample], axis=0)
    return Image.fromarray(strip).quantize(colors=colors, method=Image.Quantize.MEDIANCUT)


def write_gif(path: str | Path, images: Iterable[np.ndarray], *, fps: float = 10.0,
              palette_sample: int = 8, palette_extra: Sequence[np.ndarray] = ()) -> int:
    """Write ``images`` as a looping GIF at ``fps`` with imageio; returns the frame count.

    Every frame is mapped to one palette (made from the first ``palette_sample`` frames plus
    ``palette_extra``, e.g. :meth:`SceneRenderer.swatch` for colours that appear only later), so pixels
    that do not change are identical from frame to frame and the GIF writer stores only the changed
    region of each frame.
    """
    import imageio.v3 as iio
    from PIL import Image

    it = iter(images)
    head = [f for _, f in zip(range(palette_sample), it, strict=False)]
    if not head:
        raise ValueError("no frames to write")
    pal = shared_palette([*head, *palette_extra])
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    n = 0
    duration_ms = int(round(1000.0 / fps))
    with iio.imopen(path, "w", extension=".gif") as gif:
        for f in (*head, *it):
            q = Image.fromarray(np.asarray(f)).quantize(palette=pal, dither=Image.Dither.NONE)
            gif.write(np.asarray(q.convert("RGB")), duration=duration_ms, loop=0)
            n += 1
    return n


def goal_caption(names: Sequence[str], positions: Sequence[Sequence[float]]
                 ) -> Callable[[int, Timeline], str]:
    """A caption function: "goal i/N name: phase" for goals identified by their ``positions`` (m)."""
    pos = np.asarray(positions, dtype=float)

    def caption(t: int, tl: Timeline) -> str:
        g = tl.goal_at(t)
        phase, message = tl.phase_at(t)
        if g is None:
            return "moving to the ready pose"
        d = np.linalg.norm(pos - g[1], axis=1)
        i = int(np.argmin(d))
        label = f"goal {i + 1}/{len(names)} {names[i]}" if d[i] < 1e-6 else "goal"
        detail = f" ({message})" if phase == "rejected" and message else ""
        return f"{label}: {phase or '-'}{detail}"

    return caption


def duration_s(timeline: Timeline) -> float:
    """Recording time covered by the joint samples (s)."""
    return float(timeline.t[-1] - timeline.t[0]) / 1e9 if len(timeline.t) > 1 else 0.0


__all__ = ["DEMO_CAMERA", "SceneRenderer", "Timeline", "draw_caption", "duration_s", "frames", "goal_caption",
           "load_timeline", "shared_palette", "write_gif"]
