"""Bag tools: record a real publisher in another process, read the bag with two libraries,
play it back into the graph and compare values and timing."""

import time

import numpy as np
import pytest
from ros_helpers import SpinningNode, start_node, stop, wait_until

from terrain_nav_ros.tools import bags

N = 20
PERIOD = 0.05


def _publish_and_record(bag):
    from std_msgs.msg import String

    from terrain_nav_msgs.msg import PvaFix

    talker = SpinningNode("talker")
    try:
        pubs = (talker.node.create_publisher(String, "/chatter", 10),
                talker.node.create_publisher(PvaFix, "/nav/pva_fix", 10))
        recorder = start_node("bag_recorder",
                              {"output": str(bag), "topics": ["/chatter", "/nav/pva_fix"]})
        ok = wait_until(lambda: all(p.get_subscription_count() > 0 for p in pubs), 20)
        assert ok, "recorder never subscribed:\n" + stop(recorder)
        for i in range(N):
            pubs[0].publish(String(data=f"hello {i}"))
            pubs[1].publish(PvaFix(status=PvaFix.STATUS_POSITION, similarity=i / 10,
                                   num_pairings=i, reason=f"fix {i}",
                                   relocalisation=i % 3 == 0))
            time.sleep(PERIOD)
        time.sleep(0.5)
        log = stop(recorder)
        assert recorder.returncode == 0, log
    finally:
        talker.close()


@pytest.fixture(scope="module")
def recorded_bag(tmp_path_factory):
    bag = tmp_path_factory.mktemp("bags") / "talk"
    _publish_and_record(bag)
    return bag


def test_recorded_bag_is_readable_by_rosbags(recorded_bag):
    info = {t.topic: t for t in bags.topics(recorded_bag)}
    assert info["/chatter"].msgtype == "std_msgs/msg/String"
    assert info["/nav/pva_fix"].msgtype == "terrain_nav_msgs/msg/PvaFix"
    assert info["/chatter"].count == N and info["/nav/pva_fix"].count == N
    fixes = [bags.decode(m) for m in bags.read(recorded_bag, ["/nav/pva_fix"])]
    assert [f.num_pairings for f in fixes] == list(range(N))
    assert [f.relocalisation for f in fixes] == [i % 3 == 0 for i in range(N)]
    assert fixes[3].reason == "fix 3"
    assert "Messages:   40" in bags.info(recorded_bag)


def test_a_recorder_on_sim_time_subscribes_before_the_clock_starts(tmp_path):
    """A replay's recorder runs on the bag's clock, which starts with the bag's first
    message: it must have subscribed to the graph's outputs by then, or the answers to
    the first frames are lost (a replay's frames counted unanswered)."""
    from std_msgs.msg import String

    talker = SpinningNode("early_talker")
    try:
        pub = talker.node.create_publisher(String, "/chatter", 10)
        recorder = start_node("bag_recorder", {"output": str(tmp_path / "bag"),
                                               "topics": ["/chatter"], "use_sim_time": True})
        subscribed = wait_until(lambda: pub.get_subscription_count() > 0, 20)
        log = stop(recorder)
        assert subscribed, "recorder waited for /clock to subscribe:\n" + log
    finally:
        talker.close()


def test_a_topic_seen_before_its_publisher_is_recorded_with_the_publisher_s_qos(tmp_path):
    """A replay's recorder finds /nav/pva_fix by the ekf's subscription before the matcher
    publishes: subscribing then (no publisher to match) made it best effort, and a loaded
    machine lost answers from the bag. It must wait for the publisher and match it."""
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from std_msgs.msg import String

    latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)
    early, late = SpinningNode("early_listener"), SpinningNode("late_talker")
    try:
        early.node.create_subscription(String, "/late", lambda m: None, 10)
        recorder = start_node("bag_recorder", {"output": str(tmp_path / "bag"),
                                               "topics": ["/late"]})
        seen = wait_until(lambda: "bag_recorder" in late.node.get_node_names(), 20)
        time.sleep(1.0)   # several discovery periods with only the subscriber known
        pub = late.node.create_publisher(String, "/late", latched)
        pub.publish(String(data="latched before the recorder matched"))
        recorded = wait_until(lambda: pub.get_subscription_count() > 1, 20)
        time.sleep(0.5)
        log = stop(recorder)
        assert seen and recorded, "recorder never subscribed:\n" + log
    finally:
        early.close()
        late.close()
    (topic,) = [t for t in bags.topics(tmp_path / "bag") if t.topic == "/late"]
    assert topic.reliable and topic.transient_local
    assert [bags.decode(m).data for m in bags.read(tmp_path / "bag", ["/late"])] == [
        "latched before the recorder matched"]


def test_reading_a_topic_the_bag_lacks_yields_nothing(recorded_bag):
    assert list(bags.read(recorded_bag, ["/nav/ekf/diagnostics"])) == []
    assert len(list(bags.read(recorded_bag, ["/chatter", "/absent"]))) == N


def test_recorded_bag_is_readable_by_the_mcap_package(recorded_bag):
    from mcap.reader import make_reader

    (mcap_file,) = recorded_bag.glob("*.mcap")
    with open(mcap_file, "rb") as stream:
        reader = make_reader(stream)
        seen = [(channel.topic, schema.name) for schema, channel, _ in reader.iter_messages()]
        chunks = reader.get_summary().chunk_indexes
    assert chunks and {c.compression for c in chunks} == {"zstd"}   # the recorder's default
    assert seen.count(("/chatter", "std_msgs/msg/String")) == N
    assert seen.count(("/nav/pva_fix", "terrain_nav_msgs/msg/PvaFix")) == N


def test_play_back_preserves_values_timing_and_remaps(recorded_bag):
    from rosgraph_msgs.msg import Clock
    from std_msgs.msg import String

    listener = SpinningNode("listener")
    got, clocks = [], []
    listener.node.create_subscription(
        String, "/replayed", lambda m: got.append((time.monotonic(), m.data)), 10)
    listener.node.create_subscription(Clock, "/clock", lambda m: clocks.append(m), 10)
    try:
        player = start_node("bag_player", {"bag": str(recorded_bag),
                                           "topics": ["/chatter"],
                                           "remap": ["/chatter:=/replayed"],
                                           "wait_for_topics": ["/chatter"]})
        _played_all(player, got)
    finally:
        listener.close()
    assert [d for _, d in got] == [f"hello {i}" for i in range(N)]
    recorded = np.array([m.timestamp_ns for m in bags.read(recorded_bag, ["/chatter"])]) * 1e-9
    played = np.array([t for t, _ in got])
    # Playback keeps the recorded spacing (a behaviour, not a speed target: generous bound).
    assert np.median(np.abs(np.diff(played) - np.diff(recorded))) < 0.02
    assert clocks, "no /clock published"


def test_play_back_waits_for_a_node_to_subscribe_to_its_inputs(recorded_bag):
    """A node of the graph that is still loading its kernels (it subscribes once they are
    loaded, seconds later, while its process is already in the graph) gets every message:
    a replay of a first run must not lose its first frames."""
    from std_msgs.msg import String

    late = SpinningNode("late_node")     # in the graph at once, subscribing 3 s later
    got = []
    try:
        player = start_node("bag_player", {"bag": str(recorded_bag), "topics": ["/chatter"],
                                           "wait_for_nodes": ["late_node"],
                                           "wait_timeout": 60.0})
        time.sleep(3.0)
        late.node.create_subscription(String, "/chatter", lambda m: got.append(m.data), 10)
        _played_all(player, got)
    finally:
        late.close()
    assert got == [f"hello {i}" for i in range(N)]


def _played_all(player, got: list) -> None:
    """The player ends within 30 s with exit 0, and all N messages arrive in ``got``."""
    log = stop(player, timeout=30) if not wait_until(
        lambda: player.poll() is not None, 30) else player.communicate()[0]
    assert player.returncode == 0, log
    assert wait_until(lambda: len(got) == N, 5), f"got {len(got)} of {N}\n{log}"


def test_missing_and_damaged_bags_raise_bag_error(tmp_path, recorded_bag):
    with pytest.raises(bags.BagError, match="does not exist"):
        bags.topics(tmp_path / "nope")
    damaged = tmp_path / "damaged"
    damaged.mkdir()
    for f in recorded_bag.iterdir():
        data = f.read_bytes()
        (damaged / f.name).write_bytes(data[: len(data) // 2] if f.suffix == ".mcap" else data)
    with pytest.raises(bags.BagError):
        list(bags.read(damaged, salvage=False))



def test_a_bag_cut_short_is_salvaged_up_to_the_damage(tmp_path):
    from rosbags.typesys.stores.ros2_jazzy import std_msgs__msg__String as String

    bag, n = tmp_path / "long", 3000
    with bags.BagWriter(bag) as writer:  # several MCAP chunks
        for i in range(n):
            writer.write_message("/chatter", i * 1000, String(data=f"{i:06d}" + "x" * 1000),
                                 "std_msgs/msg/String")
    (mcap_file,) = bag.glob("*.mcap")
    mcap_file.write_bytes(mcap_file.read_bytes()[: mcap_file.stat().st_size // 2])
    salvaged = [bags.decode(m).data[:6] for m in bags.read(bag, ["/chatter"])]
    assert n // 4 < len(salvaged) < n
    assert salvaged == [f"{i:06d}" for i in range(len(salvaged))]
    assert bags.is_damaged(bag) and "DAMAGED" in bags.info(bag)


def test_the_report_reads_which_fixes_were_relocalisations(recorded_bag):
    from terrain_nav_ros.tools import report

    fixes = report._fixes(recorded_bag)
    assert [f["relocalisation"] for f in fixes] == [i % 3 == 0 for i in range(N)]


def test_the_report_lists_what_the_ekf_found_once_each(tmp_path):
    from terrain_nav_ros.tools import report

    store = bags.typestore()
    types = {name: store.types[f"diagnostic_msgs/msg/{name}"]
             for name in ("DiagnosticArray", "DiagnosticStatus", "KeyValue")}
    header = store.types["std_msgs/msg/Header"](
        stamp=store.types["builtin_interfaces/msg/Time"](sec=0, nanosec=0), frame_id="")
    found = ["never", "started from agreeing relocalisations at 13.000 s",
             "started from agreeing relocalisations at 13.000 s",
             "position reset onto agreeing relocalisations at 40.000 s: jumped 5000 m "
             "horizontally, +3 m vertically"]
    with bags.BagWriter(tmp_path / "out") as writer:
        for i, value in enumerate(found):
            status = types["DiagnosticStatus"](
                level=0, name="ekf: filter", message="ok", hardware_id="terrain_nav",
                values=[types["KeyValue"](key="found", value=value)])
            writer.write_message("/nav/ekf/diagnostics", i * 10**9,
                                 types["DiagnosticArray"](header=header, status=[status]),
                                 "diagnostic_msgs/msg/DiagnosticArray")
    assert report.navigation_events(tmp_path / "out") == found[1::2]


def test_the_report_counts_the_frames_camera_ingest_received_over_its_restarts(tmp_path):
    """A frame the bag holds but camera_ingest never received was lost on the way (a
    best-effort camera link): the report tells it from one the graph left unanswered."""
    from terrain_nav_ros.tools import report

    store = bags.typestore()
    types = {name: store.types[f"diagnostic_msgs/msg/{name}"]
             for name in ("DiagnosticArray", "DiagnosticStatus", "KeyValue")}
    header = store.types["std_msgs/msg/Header"](
        stamp=store.types["builtin_interfaces/msg/Time"](sec=0, nanosec=0), frame_id="")
    counts = [0, 4, 9, 9, 2, 6]    # a restart after 9 frames, 6 more in its second life
    with bags.BagWriter(tmp_path / "out") as writer:
        for i, count in enumerate(counts):
            status = types["DiagnosticStatus"](
                level=0, name="camera_ingest", message="ok", hardware_id="terrain_nav",
                values=[types["KeyValue"](key="frames_received", value=str(count))])
            writer.write_message("/camera_ingest/diagnostics", i * 10**9,
                                 types["DiagnosticArray"](header=header, status=[status]),
                                 "diagnostic_msgs/msg/DiagnosticArray")
    assert report.frames_received(tmp_path / "out") == 15
    text = report.format_report({"input_bag": "in", "output_bag": "out", "fixes": {
        "frames": 14, "in_bag": 17, "received": 15, "lost_on_the_way": 2, "fixes": 10,
        "no_fix": 4,
        "reasons": []}, "latency": {}, "usage": {}})
    assert "3 camera frames of the bag got no answer (2 never reached camera_ingest (lost " \
        "on the way), 1 reached it and fell behind)" in text


def test_the_report_says_when_the_unanswered_frames_came(tmp_path):
    """Frames no fix answered, in seconds after the first: the first frames (a graph or
    a recorder not yet listening) read apart from a stall or the tail."""
    from terrain_nav_ros.tools import report

    store = bags.typestore()
    image, header = (store.types[f"{t}"] for t in ("sensor_msgs/msg/CompressedImage",
                                                    "std_msgs/msg/Header"))
    time_ = store.types["builtin_interfaces/msg/Time"]
    with bags.BagWriter(tmp_path / "in") as writer:
        for k in range(6):   # frames at 100.0, 100.5, ... 102.5 s
            stamp = time_(sec=100 + k // 2, nanosec=500_000_000 * (k % 2))
            writer.write_message("/camera/image_raw/compressed", 10**9 + k * 10**8,
                                 image(header=header(stamp=stamp, frame_id="camera"),
                                       format="jpeg", data=np.zeros(4, np.uint8)),
                                 "sensor_msgs/msg/CompressedImage")
    assert report.unanswered_at(tmp_path / "in", [100.5, 101.5, 102.0]) == [0.0, 1.0, 2.5]
    assert report.unanswered_at(tmp_path / "in", [], limit=2) == [0.0, 0.5]
    text = report.format_report({"input_bag": "in", "output_bag": "out", "fixes": {
        "frames": 3, "in_bag": 6, "received": 6, "lost_on_the_way": 0, "fixes": 0,
        "no_fix": 3, "unanswered_at": [0.0, 1.0, 2.5], "reasons": []},
        "latency": {}, "usage": {}})
    assert "3 reached it and fell behind; at 0, 1, 2.5 s after the first)" in text


def test_odometry_that_stops_before_the_imu_does_is_reported(tmp_path):
    """An IMU refused mid-flight leaves odometry up to that stamp only: the report says
    where it stopped, against the bag's IMU (a gap under 5 s is the tail of the replay)."""
    from terrain_nav_ros.tools import report

    store = bags.typestore()
    string = store.types["std_msgs/msg/String"]
    with bags.BagWriter(tmp_path / "in") as writer:
        for k in range(201):                      # 20 s of IMU at 10 Hz from t = 100 s
            writer.write_message("/imu/data", (100 * 10**9) + k * 10**8, string(data=""),
                                 "std_msgs/msg/String")
    stopped = report._odometry_stopped(tmp_path / "in", 111.0)
    assert stopped == pytest.approx({"at": 11.0, "imu_end": 20.0})
    assert report._odometry_stopped(tmp_path / "in", 116.0) is None


def test_settled_after_is_when_the_error_stays_below_the_bound():
    from terrain_nav_ros.tools import report

    t = np.arange(6.0)
    assert report.settled_after(t, [90, 50, 70, 40, 30, 20], 60.0) == 3.0
    assert report.settled_after(t, [10] * 6, 60.0) == 0.0
    assert np.isnan(report.settled_after(t, [10, 10, 10, 10, 10, 70], 60.0))
    assert np.isnan(report.settled_after(np.array([]), [], 60.0))


def test_fix_nees_is_chi_square_for_true_covariances_and_skips_unusable_ones():
    """Errors drawn from their own covariances give NEES with mean ~2 (chi-square, 2 degrees
    of freedom); covariances ten times too wide give a hundredth; a covariance that is NaN or
    singular (a fix without one) is left out, not counted as zero."""
    from terrain_nav_ros.tools import report

    rng = np.random.default_rng(0)
    cov = np.array([[400.0, 150.0], [150.0, 100.0]])
    offsets = rng.multivariate_normal([0.0, 0.0], cov, 4000)
    nees = report.normalised_errors(offsets, np.repeat(cov[None], len(offsets), axis=0))
    assert np.mean(nees) == pytest.approx(2.0, rel=0.08)
    assert np.median(nees) == pytest.approx(2 * np.log(2), rel=0.08)
    wide = report.normalised_errors(offsets, np.repeat(100 * cov[None], len(offsets), axis=0))
    assert np.mean(wide) == pytest.approx(0.02, rel=0.08)
    unusable = np.array([np.full((2, 2), np.nan), np.zeros((2, 2)), -np.eye(2), cov])
    assert report.normalised_errors(offsets[:4], unusable) == pytest.approx(
        [offsets[3] @ np.linalg.solve(cov, offsets[3])])
    assert len(report.normalised_errors(np.empty((0, 2)), np.empty((0, 2, 2)))) == 0


def test_a_changed_copy_keeps_drops_and_replaces_messages(tmp_path):
    from rosbags.typesys.stores.ros2_jazzy import std_msgs__msg__String as String

    bag = tmp_path / "talk"
    with bags.BagWriter(bag) as writer:
        for i in range(30):
            writer.write_message("/chatter", i * 100_000_000, String(data=str(i)),
                                 "std_msgs/msg/String")
            writer.write_message("/noise", i * 100_000_000, String(data="x"),
                                 "std_msgs/msg/String")
    (bag / "mission.yaml").write_text("name: talk\n")

    def change(topic, at, decode):
        if topic == "/noise":
            return "drop"
        if at >= 2.0:
            msg = decode()
            msg.data += "!"
            return msg
        return None

    copy = bags.changed_copy(bag, tmp_path / "copy", change)
    assert {t.topic: t.count for t in bags.topics(copy)} == {"/chatter": 30, "/noise": 0}
    texts = [bags.decode(m).data for m in bags.read(copy)]
    assert texts == [str(i) for i in range(20)] + [f"{i}!" for i in range(20, 30)]
    assert (copy / "mission.yaml").read_text() == "name: talk\n"


@pytest.mark.parametrize("compress", [True, False])
def test_a_flushed_recording_survives_its_writer_being_killed(tmp_path, compress):
    """What a recorder had flushed (every second) is in the file, readable as a bag cut
    short, though the writer never closed it (SIGKILL): before, a short recording left
    0 bytes. Compressed chunks are salvaged as well."""
    import shutil

    from rosbags.typesys.stores.ros2_jazzy import std_msgs__msg__String as String

    writer = bags.BagWriter(tmp_path / "live", compress=compress)
    writer.open()
    for i in range(5):
        writer.write_message("/chatter", 10**9 + i, String(data=f"hello {i}"),
                             "std_msgs/msg/String")
    writer.flush()
    writer.write_message("/chatter", 10**9 + 5, String(data="lost"), "std_msgs/msg/String")
    # the file as a SIGKILL would leave it: no footer, no metadata.yaml
    (tmp_path / "killed").mkdir()
    shutil.copy(tmp_path / "live" / "live.mcap", tmp_path / "killed" / "killed.mcap")
    assert bags.is_damaged(tmp_path / "killed")
    got = [bags.decode(m).data for m in bags.read(tmp_path / "killed", ["/chatter"])]
    assert got == [f"hello {i}" for i in range(5)]
    writer.close()


def _zero_message(store, msgtype):
    """A message of ``msgtype`` with every field zero or empty, by ``store``'s definitions."""
    from rosbags.typesys.base import Nodetype

    def value(desc):
        kind, detail = desc
        if kind == Nodetype.NAME:
            return _zero_message(store, detail)
        if kind == Nodetype.BASE:
            return {"string": "", "bool": False}.get(detail[0], 0.0 if "float" in detail[0]
                                                      else 0)
        sub, length = detail   # an array or a sequence: of base types here
        dtype = np.dtype(sub[1][0]) if sub[0] == Nodetype.BASE else object
        return np.zeros(length if kind == Nodetype.ARRAY else 0, dtype)

    _, fields = store.fielddefs[msgtype]
    return store.types[msgtype](**{name: value(desc) for name, desc in fields})


def test_a_bag_recorded_before_a_message_gained_a_field_is_read_as_it_was_written(tmp_path):
    """PvaFix gained mosaic_lag after bags were recorded with it. Such a bag stores its own
    definition: read by that, its fixes keep their values, not a size mismatch or fields
    shifted into the next ones."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    pva = "terrain_nav_msgs/msg/PvaFix"
    current, _ = bags.typestore().generate_msgdef(pva, ros_version=2)
    before = "\n".join(line for line in current.splitlines() if line != "float64 mosaic_lag")
    old = get_typestore(Stores.EMPTY)
    old.register(get_types_from_msg(before, pva))
    fix = _zero_message(old, pva)
    fix.status, fix.projection_height, fix.latitude, fix.reason = 1, 2500.0, 44.5, "old"
    bag = tmp_path / "old"
    with Writer(bag, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        conn = writer.add_connection("/nav/pva_fix", pva, typestore=old)
        writer.write(conn, 1_000, old.serialize_cdr(fix, pva))
    (message,) = bags.read(bag, ["/nav/pva_fix"])
    got = bags.decode(message)
    assert (got.status, got.projection_height, got.latitude, got.reason) == \
        (1, 2500.0, 44.5, "old")
    assert not hasattr(got, "mosaic_lag")
    # a message of the project's own definition is decoded by the project's store
    assert bags.store_for(pva, current) is bags.typestore()
