"""MCAP files in the ROS 2 profile, the way ``ros2 bag record -s mcap`` writes them (no ROS here).

* header profile ``ros2``; one schema per message type: name ``pkg/msg/Type``, encoding ``ros2msg``,
  data the complete ``.msg`` definition (:mod:`redarm_ros.record.schema`);
* one channel per topic: message encoding ``cdr``, metadata ``offered_qos_profiles`` (the publishers'
  QoS as rosbag2's YAML, enum values as integers, the form every rosbag2 reader accepts when the file
  carries no ``rosbag2`` metadata record) and ``topic_type_hash`` (``RIHS01_...``) when known;
* messages: the serialized CDR bytes as received, ``log_time`` the receive time and ``publish_time``
  the same (ns since the epoch), chunked and zstd-compressed, with message indexes and statistics.

:class:`Ros2McapWriter` takes raw CDR (what an rclpy ``raw=True`` subscription hands over) or, with
:meth:`Ros2McapWriter.write_dict`, a plain dict encoded by mcap-ros2-support's dynamic CDR encoder
from the schema text (used for ``tf2_msgs/TFMessage``, whose Python package may be missing).
:func:`summarize` reads a file back (topics, schemas, counts, time order) with the mcap reader.
"""

from __future__ import annotations

import threading
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from redarm_ros.errors import InvalidInputError
from redarm_ros.record.schema import normalize_type, ros2msg_definition

PROFILE = "ros2"
LIBRARY = "redarm_ros redarm-record"

# rmw enum values (rmw/types.h; rclpy's QoS policy enums carry the same numbers).
HISTORY = {"system_default": 0, "keep_last": 1, "keep_all": 2}
RELIABILITY = {"system_default": 0, "reliable": 1, "best_effort": 2}
DURABILITY = {"system_default": 0, "transient_local": 1, "volatile": 2}
LIVELINESS = {"system_default": 0, "automatic": 1, "manual_by_topic": 3}
INFINITE_NS = 9223372036854775807  # RMW_DURATION_INFINITE


@dataclass(frozen=True)
class QosOffer:
    """One publisher's offered QoS (what goes into ``offered_qos_profiles``). Durations in ns."""

    history: int = HISTORY["keep_last"]
    depth: int = 10
    reliability: int = RELIABILITY["reliable"]
    durability: int = DURABILITY["volatile"]
    deadline_ns: int = INFINITE_NS
    lifespan_ns: int = INFINITE_NS
    liveliness: int = LIVELINESS["automatic"]
    liveliness_lease_ns: int = INFINITE_NS

    def yaml_entry(self) -> str:
        """This profile as one item of rosbag2's ``offered_qos_profiles`` YAML list."""

        def dur(ns: int) -> str:
            return f"\n    sec: {ns // 1_000_000_000}\n    nsec: {ns % 1_000_000_000}"

        return (f"- history: {self.history}\n  depth: {self.depth}\n  reliability: {self.reliability}\n"
                f"  durability: {self.durability}\n  deadline:{dur(self.deadline_ns)}\n"
                f"  lifespan:{dur(self.lifespan_ns)}\n  liveliness: {self.liveliness}\n"
                f"  liveliness_lease_duration:{dur(self.liveliness_lease_ns)}\n"
                "  avoid_ros_namespace_conventions: false")


def qos_yaml(offers: Sequence[QosOffer]) -> str:
    """``offered_qos_profiles`` text for a topic's publishers (empty string for none)."""
    return "\n".join(o.yaml_entry() for o in offers)


class Ros2McapWriter:
    """A ROS 2 MCAP file being written; thread-safe; use as a context manager or call :meth:`close`.

    Raises:
        OSError: the file cannot be created.
    """

    def __init__(self, path: str | Path, *, compression: str = "zstd", chunk_size: int = 1 << 20) -> None:
        from mcap.writer import CompressionType, Writer

        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._fh = open(self.path, "wb")  # noqa: SIM115 - closed in close()
        comp = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}
        if compression not in comp:
            raise InvalidInputError(f"compression must be one of {sorted(comp)}", field="compression",
                                    value=compression)
        self._w = Writer(self._fh, chunk_size=chunk_size, compression=comp[compression])
        self._w.start(profile=PROFILE, library=LIBRARY)
        self._lock = threading.Lock()
        self._schemas: dict[str, int] = {}
        self._schema_text: dict[str, str] = {}
        self._channels: dict[str, tuple[int, str]] = {}
        self._encoders: dict[str, Any] = {}
        self._last_log_time = 0
        self.counts: dict[str, int] = {}
        self.closed = False

    # -- topics ---------------------------------------------------------------------------------------
    def add_topic(self, topic: str, type_name: str, *, offers: Sequence[QosOffer] = (),
                  type_hash: str = "", definition: str | None = None) -> int:
        """Register ``topic`` of ``type_name`` (pkg/msg/Type); returns its channel id (idempotent).

        ``definition`` overrides the ``ros2msg`` text (default: built from the installed .msg files).

        Raises:
            InvalidInputError: bad type name, no definition found, or the topic exists with another type.
        """
        full = normalize_type(type_name)
        with self._lock:
            if topic in self._channels:
                cid, known = self._channels[topic]
                if known != full:
                    raise InvalidInputError(f"{topic} is recorded as {known}, not {full}", field="type",
                                            value=type_name)
                return cid
            if full not in self._schemas:
                text = definition if definition is not None else ros2msg_definition(full)
                self._schemas[full] = self._w.register_schema(full, "ros2msg", text.encode("utf-8"))
                self._schema_text[full] = text
            meta = {"offered_qos_profiles": qos_yaml(offers)}
            if type_hash:
                meta["topic_type_hash"] = type_hash
            cid = self._w.register_channel(topic, "cdr", self._schemas[full], meta)
            self._channels[topic] = (cid, full)
            self.counts[topic] = 0
            return cid

    def has_topic(self, topic: str) -> bool:
        """True once ``topic`` has a channel."""
        with self._lock:
            return topic in self._channels

    # -- messages -------------------------------------------------------------------------------------
    def write(self, topic: str, data: bytes, log_time_ns: int, publish_time_ns: int | None = None) -> None:
        """Append one serialized (CDR) message of a registered ``topic``.

        Log times are kept non-decreasing within the file (a time before the previous one is raised to
        it), so readers see the messages in receive order.
        """
        with self._lock:
            if self.closed:
                return
            cid, _ = self._channels[topic]
            t = max(int(log_time_ns), self._last_log_time)
            self._last_log_time = t
            self.counts[topic] += 1
            self._w.add_message(cid, log_time=t, data=bytes(data),
                                publish_time=t if publish_time_ns is None else int(publish_time_ns),
                                sequence=self.counts[topic])

    def write_dict(self, topic: str, message: Mapping[str, Any], log_time_ns: int) -> None:
        """CDR-encode ``message`` (nested dicts/lists by field name) with the topic's schema, then
        :meth:`write` it."""
        from mcap_ros2._dynamic import serialize_dynamic  # mcap-ros2-support's schema-driven encoder

        with self._lock:
            full = self._channels[topic][1]
            enc = self._encoders.get(full)
            if enc is None:
                enc = serialize_dynamic(full, self._schema_text[full])[full]
                self._encoders[full] = enc
        self.write(topic, enc(message), log_time_ns)

    def close(self) -> None:
        """Write the summary (indexes, statistics) and close the file; safe to call twice."""
        with self._lock:
            if self.closed:
                return
            self.closed = True
            self._w.finish()
            self._fh.close()

    def __enter__(self) -> Ros2McapWriter:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()


@dataclass
class TopicSummary:
    """One topic of a recording as read back."""

    topic: str
    schema_name: str
    schema_encoding: str
    message_encoding: str
    count: int = 0
    first_ns: int = 0
    last_ns: int = 0
    monotonic: bool = True  # log times never decrease along the file
    metadata: dict[str, str] = field(default_factory=dict)


def summarize(path: str | Path) -> tuple[str, dict[str, TopicSummary]]:
    """Read a whole MCAP file in file order: (header profile, topic -> :class:`TopicSummary`).

    ``monotonic`` of each topic is whether its log times never decrease; the key ``"*"`` summarizes
    every message of the file the same way.
    """
    from mcap.reader import make_reader

    topics: dict[str, TopicSummary] = {}
    every = TopicSummary("*", "", "", "")
    with open(path, "rb") as fh:
        reader = make_reader(fh)
        profile = reader.get_header().profile
        for schema, channel, message in reader.iter_messages(log_time_order=False):
            ts = topics.get(channel.topic)
            if ts is None:
                ts = topics[channel.topic] = TopicSummary(
                    channel.topic, schema.name if schema else "", schema.encoding if schema else "",
                    channel.message_encoding, metadata=dict(channel.metadata))
            for s in (ts, every):
                if s.count and message.log_time < s.last_ns:
                    s.monotonic = False
                if not s.count:
                    s.first_ns = message.log_time
                s.count += 1
                s.last_ns = message.log_time
    topics["*"] = every
    return profile, topics


def read_messages(path: str | Path, topics: Sequence[str] | None = None) -> list[tuple[str, int, Any]]:
    """Decode messages (mcap-ros2-support's dynamic decoder): (topic, log_time ns, message) in log-time
    order, optionally only of ``topics``."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    with open(path, "rb") as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        decoded = reader.iter_decoded_messages(topics, log_time_order=True)
        return [(channel.topic, message.log_time, msg) for _schema, channel, message, msg in decoded]
