"""rosbag2 MCAP bags without rosbag2_py: reading, writing and decoding with ``rosbags``.

The bags this module writes are ordinary rosbag2 (metadata version 9, MCAP storage) bags:
``ros2 bag``, Foxglove and the ``mcap`` package read them. The type store knows every ROS 2
Jazzy standard message plus this project's ``terrain_nav_msgs`` and the vendored PX4
messages (``vendor/px4_msgs``), so the autopilot bridge's output can be recorded. A message is
decoded with the definition its bag stores where that differs from the project's (a bag
recorded before a message gained a field): read as it was written, never misread.
"""

from __future__ import annotations

import functools
import struct
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

from rosbags.interfaces import (
    MessageDefinitionFormat,
    Qos,
    QosDurability,
    QosHistory,
    QosLiveliness,
    QosReliability,
    QosTime,
)
from rosbags.rosbag2 import CompressionFormat, CompressionMode, Reader, StoragePlugin, Writer
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

MSGS_SOURCE = Path(__file__).resolve().parents[2] / "terrain_nav_msgs"
PX4_MSGS_SOURCE = Path(__file__).resolve().parents[2] / "vendor" / "px4_msgs"


class BagError(RuntimeError):
    """A bag cannot be opened, read or written; the message names the file and the cause."""


def _msg_dirs() -> list[Path]:
    """Where terrain_nav_msgs' .msg files are: the installed share, else the source tree."""
    dirs = []
    try:
        from ament_index_python.packages import get_package_share_directory

        dirs.append(Path(get_package_share_directory("terrain_nav_msgs")) / "msg")
    except Exception:  # noqa: BLE001 - not installed through ament: use the sources
        pass
    dirs.append(MSGS_SOURCE / "msg")
    return [d for d in dirs if d.is_dir()]


@functools.cache
def typestore():
    """Jazzy type store with terrain_nav_msgs and px4_msgs registered (cached)."""
    store = get_typestore(Stores.ROS2_JAZZY)
    dirs = _msg_dirs()
    if not dirs:
        raise BagError("terrain_nav_msgs .msg files not found (run scripts/setup.sh)")
    types = {}
    for path in sorted(dirs[0].glob("*.msg")):
        types.update(get_types_from_msg(path.read_text(), f"terrain_nav_msgs/msg/{path.stem}"))
    for path in sorted((PX4_MSGS_SOURCE / "msg").glob("*.msg")):
        types.update(get_types_from_msg(path.read_text(), f"px4_msgs/msg/{path.stem}"))
    store.register(types)
    return store


def qos_profile(reliable: bool = True, transient_local: bool = False, depth: int = 10) -> Qos:
    """A rosbags QoS record for a topic's offered_qos_profiles metadata."""
    never = QosTime(sec=0x7FFFFFFF, nsec=0xFFFFFFFF)
    return Qos(
        history=QosHistory.KEEP_LAST, depth=depth,
        reliability=QosReliability.RELIABLE if reliable else QosReliability.BEST_EFFORT,
        durability=QosDurability.TRANSIENT_LOCAL if transient_local else QosDurability.VOLATILE,
        deadline=never, lifespan=never, liveliness=QosLiveliness.AUTOMATIC,
        liveliness_lease_duration=never, avoid_ros_namespace_conventions=False)


@dataclass(frozen=True)
class BagMessage:
    """One serialized message of a bag."""

    topic: str
    msgtype: str
    timestamp_ns: int
    rawdata: bytes
    msgdef: str = ""    # the bag's own definition of msgtype (ros2msg text); "" unknown


@dataclass(frozen=True)
class TopicInfo:
    """What a bag holds on one topic."""

    topic: str
    msgtype: str
    count: int
    reliable: bool
    transient_local: bool


class BagWriter:
    """Write serialized messages to a new rosbag2 MCAP bag (a directory).

    Use as a context manager so the MCAP summary and metadata.yaml are written on exit.
    ``compress`` zstd-compresses the MCAP chunks (what ``ros2 bag record
    --compression-mode storage`` would do; every MCAP reader decompresses them).
    """

    def __init__(self, path: str | Path, compress: bool = False):
        self.path = Path(path)
        if self.path.exists():
            raise BagError(f"bag {self.path} already exists; choose a new output path")
        self._writer = Writer(self.path, version=9, storage_plugin=StoragePlugin.MCAP)
        if compress:
            self._writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
        self._connections = {}
        self._open = False

    def __enter__(self) -> BagWriter:
        self.open()
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def open(self) -> None:
        self._writer.open()
        self._open = True

    def close(self) -> None:
        if self._open:
            self._writer.close()
            self._open = False

    def flush(self) -> None:
        """Write the messages so far to the file as a chunk of their own: a recorder killed
        with SIGKILL then loses only what came after (the MCAP writer holds up to 1 MB in
        memory, and nothing reached the file of a short recording); the bag it leaves is
        read as cut short (:func:`read` salvages its chunks)."""
        # rosbags' MCAP writer closes a chunk at 1 MB only; no public call for it
        storage = getattr(self._writer, "storage", None)
        if not self._open or storage is None or not hasattr(storage, "close_chunk"):
            return
        if storage.chunk.msgs:
            storage.close_chunk()
        storage.bio.flush()

    def has_topic(self, topic: str) -> bool:
        return topic in self._connections

    def add_topic(self, topic: str, msgtype: str, qos: Qos | None = None) -> None:
        """Declare a topic; ``msgtype`` like ``sensor_msgs/msg/Image``."""
        if topic in self._connections:
            return
        store = typestore()
        if msgtype not in store.types:
            raise BagError(f"message type {msgtype} of {topic} is unknown to the type store")
        self._connections[topic] = self._writer.add_connection(
            topic, msgtype, typestore=store, offered_qos_profiles=[qos or qos_profile()])

    def add_topics_of(self, bag: str | Path) -> None:
        """Declare every topic of ``bag``, with its QoS (to write an edited copy of it)."""
        for t in topics(bag):
            self.add_topic(t.topic, t.msgtype, qos_profile(t.reliable, t.transient_local))

    def write(self, topic: str, timestamp_ns: int, rawdata: bytes) -> None:
        """Append one CDR-serialized message (topic must have been added)."""
        self._writer.write(self._connections[topic], int(timestamp_ns), rawdata)

    def write_message(self, topic: str, timestamp_ns: int, msg, msgtype: str) -> None:
        """Serialize a rosbags message object and append it (adds the topic if needed)."""
        if not self.has_topic(topic):
            self.add_topic(topic, msgtype)
        self.write(topic, timestamp_ns, typestore().serialize_cdr(msg, msgtype))


def changed_copy(bag: str | Path, dest: str | Path, change) -> Path:
    """A copy of ``bag`` at ``dest`` (with the bag folder's mission.yaml, if any) whose
    messages go through ``change(topic, seconds since the first message, decode)``: None
    keeps one as it is, ``"drop"`` drops it, a message object replaces it (``decode()``
    gives the original, decoded). To replay a bag with a fault put in."""
    bag, dest = Path(bag), Path(dest)
    first = None
    with BagWriter(dest, compress=True) as writer:
        writer.add_topics_of(bag)
        for m in read(bag):
            first = m.timestamp_ns if first is None else first
            out = change(m.topic, (m.timestamp_ns - first) * 1e-9, lambda m=m: decode(m))
            if out is None:
                writer.write(m.topic, m.timestamp_ns, m.rawdata)
            elif not isinstance(out, str):
                writer.write_message(m.topic, m.timestamp_ns, out, m.msgtype)
    if (bag / "mission.yaml").is_file():
        (dest / "mission.yaml").write_bytes((bag / "mission.yaml").read_bytes())
    return dest


def _mcap_file(path: Path) -> Path | None:
    files = sorted(path.glob("*.mcap")) if path.is_dir() else [path]
    return files[0] if files and files[0].suffix == ".mcap" else None


def _salvage(path: Path) -> Iterator[BagMessage]:
    """Messages of an MCAP file whose end is missing (recording cut short), in file order.

    rosbags needs the summary at the end of the file; the ``mcap`` package's stream reader
    walks the records from the start instead, so everything before the damage is kept.
    """
    from mcap.exceptions import McapError
    from mcap.records import Channel, Message, Schema
    from mcap.stream_reader import StreamReader

    schemas, channels = {}, {}
    with open(path, "rb") as stream:
        try:
            for record in StreamReader(stream, emit_chunks=False).records:
                if isinstance(record, Schema):
                    msgdef = record.data.decode(errors="replace") \
                        if record.encoding == "ros2msg" else ""
                    schemas[record.id] = (record.name, msgdef)
                elif isinstance(record, Channel):
                    channels[record.id] = (record.topic,
                                           *schemas.get(record.schema_id, ("", "")))
                elif isinstance(record, Message) and record.channel_id in channels:
                    topic, msgtype, msgdef = channels[record.channel_id]
                    yield BagMessage(topic, msgtype, record.log_time, bytes(record.data),
                                     msgdef)
        except (McapError, EOFError, ValueError, OSError, struct.error):
            return  # the damaged tail (a record cut inside its length fields: struct.error)


def _salvaged_topics(path: Path) -> list[TopicInfo]:
    counts: dict[tuple[str, str], int] = {}
    for m in _salvage(path):
        counts[(m.topic, m.msgtype)] = counts.get((m.topic, m.msgtype), 0) + 1
    # QoS profiles live in the lost summary: assume reliable, latched only for /tf_static.
    return [TopicInfo(t, mt, n, True, t == "/tf_static") for (t, mt), n in counts.items()]


def _open_or_salvage(path: str | Path) -> Reader | Path:
    """An open Reader, or the path of an MCAP file that only the salvage reader can read."""
    try:
        return _open_reader(path)
    except BagError:
        mcap = _mcap_file(Path(path))
        if mcap is None or not mcap.is_file():
            raise
        return mcap


def is_damaged(path: str | Path) -> bool:
    """True when the bag cannot be opened normally but its MCAP records can be salvaged."""
    opened = _open_or_salvage(path)
    if isinstance(opened, Path):
        return True
    opened.close()
    return False


@dataclass(frozen=True)
class BagHealth:
    """What :func:`verify` found reading a whole bag.

    Attributes
    ----------
    problem : str
        Why the bag is damaged ("" when it is not).
    readable : int
        Messages readable (from the start, up to any damage).
    expected : int or None
        Messages the MCAP summary promises (None when the summary is lost).
    """

    problem: str
    readable: int
    expected: int | None

    @property
    def damaged(self) -> bool:
        return bool(self.problem)

    def describe(self) -> str:
        """One line: the damage and what is left, or that the bag is whole."""
        if not self.damaged:
            return f"whole: {self.readable} messages read and checked"
        of = f" of {self.expected}" if self.expected is not None else ""
        return f"DAMAGED: {self.problem}; {self.readable}{of} messages readable"


def verify(path: str | Path) -> BagHealth:
    """Read every message of a bag, decompressing and CRC-checking every chunk.

    Opening a bag reads only its metadata and summary, so a bag with corrupted bytes inside
    looked whole and failed halfway through a replay (issue 22). Raises BagError when
    ``path`` is no bag at all.
    """
    path = Path(path)
    if not path.exists():
        raise BagError(f"bag {path} does not exist")
    mcap = _mcap_file(path)
    if mcap is None or not mcap.is_file():
        raise BagError(f"{path} holds no .mcap file: not a rosbag2 MCAP bag")
    missing_meta = path.is_dir() and not (path / "metadata.yaml").is_file()
    problem, expected = _check_mcap(mcap)
    if missing_meta and not problem:
        problem = "metadata.yaml is missing (rosbag2 tools will not open it)"
    if not problem:
        return BagHealth("", expected, expected)
    readable = 0
    try:
        for _ in read(path):   # what a player gets: up to the damage, or salvaged
            readable += 1
    except BagError:
        pass
    return BagHealth(problem, readable, expected)


_MCAP_MAGIC = b"\x89MCAP0\r\n"


def _unreadable_mcap(stream, err) -> str:
    """Why an MCAP file without a usable summary is unreadable, from its magic bytes."""
    stream.seek(0)
    if stream.read(len(_MCAP_MAGIC)) != _MCAP_MAGIC:
        return "not an MCAP file (no MCAP magic at its start)"
    stream.seek(max(stream.seek(0, 2) - len(_MCAP_MAGIC), 0))
    if stream.read() != _MCAP_MAGIC:
        return "the MCAP file has no end (recording cut short)"
    return f"unreadable MCAP: {err}"


def _check_mcap(mcap: Path) -> tuple[str, int | None]:
    """(problem or "", messages the summary promises) of one MCAP file, read in full."""
    from mcap.reader import make_reader

    count, expected = 0, None
    with open(mcap, "rb") as stream:
        try:
            reader = make_reader(stream, validate_crcs=True)
            summary = reader.get_summary()
            if summary is not None and summary.statistics is not None:
                expected = summary.statistics.message_count
            for _ in reader.iter_messages(log_time_order=False):
                count += 1
        # mcap and its decompressors raise their own types (McapError, ZstdError, ...)
        except Exception as err:  # noqa: BLE001
            if expected is None:
                return _unreadable_mcap(stream, err), None
            return f"corrupt data: {err}", expected
    if expected is None:
        return "the MCAP file has no summary (recording cut short)", None
    if count != expected:
        return f"{count} messages where the summary promises {expected}", expected
    return "", expected


def _open_reader(path: str | Path) -> Reader:
    path = Path(path)
    if not path.exists():
        raise BagError(f"bag {path} does not exist")
    try:
        reader = Reader(path)
        reader.open()
    except Exception as err:  # rosbags raises several types for damaged bags
        raise BagError(f"cannot open bag {path}: {err}") from err
    return reader


def topics(path: str | Path) -> list[TopicInfo]:
    """Topics of a bag with their types, counts and offered QoS.

    A bag whose MCAP file was cut short is salvaged (see :func:`read`).
    """
    reader = _open_or_salvage(path)
    if isinstance(reader, Path):
        return _salvaged_topics(reader)
    try:
        out = []
        for conn in reader.connections:
            profiles = list(getattr(conn.ext, "offered_qos_profiles", []) or [])
            out.append(TopicInfo(
                conn.topic, conn.msgtype, conn.msgcount,
                reliable=all(p.reliability != QosReliability.BEST_EFFORT for p in profiles),
                transient_local=bool(profiles) and all(
                    p.durability == QosDurability.TRANSIENT_LOCAL for p in profiles)))
        return out
    finally:
        reader.close()


def read(path: str | Path, topic_names: Iterable[str] | None = None, *,
         salvage: bool = True) -> Iterator[BagMessage]:
    """Messages of a bag in timestamp order, optionally only some topics.

    A bag whose MCAP file lost its end (a recording cut short) yields, with ``salvage``, the
    messages before the damage in file order; otherwise it raises BagError. Damage inside the
    data raises BagError after the messages before it.
    """
    wanted = set(topic_names) if topic_names else None
    reader = _open_or_salvage(path) if salvage else _open_reader(path)
    if isinstance(reader, Path):
        for m in _salvage(reader):
            if wanted is None or m.topic in wanted:
                yield m
        return
    try:
        conns = [c for c in reader.connections if wanted is None or c.topic in wanted]
        if not conns:   # rosbags reads an empty list of connections as all of them
            return
        try:
            for conn, timestamp, raw in reader.messages(connections=conns):
                yield BagMessage(conn.topic, conn.msgtype, timestamp, bytes(raw),
                                 _definition(conn))
        except Exception as err:
            raise BagError(f"bag {path} is damaged: {err}") from err
    finally:
        reader.close()


def _definition(conn) -> str:
    """A reader connection's own message definition (ros2msg text), or ""."""
    msgdef = getattr(conn, "msgdef", None)
    return msgdef.data if msgdef is not None and \
        msgdef.format == MessageDefinitionFormat.MSG else ""


def decode(message: BagMessage):
    """Deserialize a bag message into a rosbags message object, by the definition its bag
    stores where that differs from the project's (:func:`store_for`)."""
    return store_for(message.msgtype, message.msgdef).deserialize_cdr(message.rawdata,
                                                                      message.msgtype)


@functools.lru_cache(maxsize=256)
def store_for(msgtype: str, msgdef: str = ""):
    """The type store to decode ``msgtype`` with: the project's (:func:`typestore`), or one
    of the bag's own definition ``msgdef`` where it defines the type, or a type the type
    holds, otherwise (a bag recorded by another version of terrain_nav_msgs: its bytes are
    laid out by its definition, and the project's would misread them or fail on them)."""
    store = typestore()
    if not msgdef:
        return store
    try:
        types = get_types_from_msg(msgdef, msgtype)
    except Exception:  # noqa: BLE001 - a definition rosbags cannot parse: the project's
        return store
    if all(store.fielddefs.get(name) == fields for name, fields in types.items()):
        return store
    own = get_typestore(Stores.EMPTY)
    own.register(types)
    return own


def info(path: str | Path, health: BagHealth | None = None) -> str:
    """Human-readable summary like ``ros2 bag info``, with what :func:`verify` found."""
    health = health or verify(path)
    reader = _open_or_salvage(path)
    if isinstance(reader, Path):
        lines = [f"Bag:        {Path(path)}",
                 f"Health:     {health.describe()}; salvageable:"]
        for t in sorted(_salvaged_topics(reader), key=lambda t: t.topic):
            lines.append(f"  {t.topic:32s} {t.msgtype:40s} {t.count:8d} msgs")
        return "\n".join(lines)
    try:
        duration = reader.duration * 1e-9 if reader.message_count else 0.0
        lines = [f"Bag:        {Path(path)}",
                 f"Duration:   {duration:.3f} s",
                 f"Start:      {reader.start_time * 1e-9:.3f} s" if reader.message_count else
                 "Start:      -",
                 f"Messages:   {reader.message_count}",
                 f"Health:     {health.describe()}",
                 "Topics:"]
        for conn in sorted(reader.connections, key=lambda c: c.topic):
            lines.append(f"  {conn.topic:32s} {conn.msgtype:40s} {conn.msgcount:8d} msgs")
        return "\n".join(lines)
    finally:
        reader.close()
