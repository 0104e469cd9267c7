"""`mapkit fly` over real DDS (Cyclone) on the loopback interface only: multicast off, localhost the only
peer, a domain id of its own per test process. Frames converted both ways against hand-worked values;
messages round-tripped through the DDS types; a simulated vehicle flown by the node; faults."""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from mapkit.flight import Setpoint
from mapkit.fly import (
    DdsConfig,
    FlyConfig,
    FlyError,
    Link,
    R_world_body_from_px4,
    _inputs,
    _outputs,
    dds_type,
    dds_typename,
    decode,
    encode,
    enu_to_ned,
    message,
    ned_to_enu,
    px4_quaternion,
    setpoint_from_px4,
    typestore,
    yaw_enu_to_ned,
    yaw_ned_to_enu,
)

LOOPBACK_XML = """<CycloneDDS xmlns="https://cdds.io/config"><Domain Id="any"><General>
<Interfaces><NetworkInterface name="lo"/></Interfaces><AllowMulticast>false</AllowMulticast></General>
<Discovery><ParticipantIndex>auto</ParticipantIndex><Peers><Peer address="localhost"/></Peers></Discovery>
</Domain></CycloneDDS>"""


@pytest.fixture(scope="session", autouse=True)
def loopback_only(tmp_path_factory: pytest.TempPathFactory) -> None:
    """Any participant made without mapkit's own config (a subprocess, a stray default) also stays on lo."""
    path = tmp_path_factory.mktemp("dds") / "cyclonedds.xml"
    path.write_text(LOOPBACK_XML)
    os.environ["CYCLONEDDS_URI"] = path.as_uri()


_LINKS: list[Link] = []


def _kept(link: Link) -> Link:
    """`link`, kept alive until the test process ends: Cyclone entities torn down by the garbage
    collector while another test runs can disturb it."""
    _LINKS.append(link)
    return link


def _domain() -> int:
    """A domain of this test process's own (pytest-xdist workers run side by side)."""
    worker = os.environ.get("PYTEST_XDIST_WORKER", "gw9")
    return 150 + 7 * int(worker[2:] or 0) % 80


# -- messages and frames -----------------------------------------------------------------------------------
def test_px4_messages_parse_from_their_own_definitions() -> None:
    store = typestore()
    names = [f for f, _ in store.fielddefs["px4_msgs/msg/TrajectorySetpoint"][1]]
    assert names == ["timestamp", "position", "velocity", "acceleration", "jerk", "yaw", "yawspeed"]
    assert dds_typename("px4_msgs/msg/VehicleOdometry") == "px4_msgs::msg::dds_::VehicleOdometry_"
    with pytest.raises(FlyError, match="unknown"):
        dds_type("foo_msgs/msg/Bar")


@pytest.mark.parametrize("msgtype", ["sensor_msgs/msg/Image", "nav_msgs/msg/Path", "px4_msgs/msg/TrajectorySetpoint",
                                     "trajectory_msgs/msg/MultiDOFJointTrajectory", "tf2_msgs/msg/TFMessage"])
def test_dds_samples_carry_the_cdr_unchanged(msgtype: str) -> None:
    msg = _example(msgtype)
    raw = encode(msg, msgtype)
    kind = dds_type(msgtype)
    assert kind.deserialize(raw).serialize() == raw
    assert encode(decode(raw, msgtype), msgtype) == raw


def test_a_truncated_message_is_a_fly_error() -> None:
    raw = encode(_example("sensor_msgs/msg/Image"), "sensor_msgs/msg/Image")
    with pytest.raises(FlyError, match="does not decode"):
        decode(raw[:40], "sensor_msgs/msg/Image")


def test_enu_ned_by_hand_and_back() -> None:
    np.testing.assert_array_equal(enu_to_ned([1.0, 2.0, 3.0]), [2.0, 1.0, -3.0])
    np.testing.assert_array_equal(ned_to_enu(enu_to_ned([1.0, 2.0, 3.0])), [1.0, 2.0, 3.0])
    assert yaw_enu_to_ned(0.0) == pytest.approx(math.pi / 2)  # facing east
    assert yaw_enu_to_ned(math.pi / 2) == pytest.approx(0.0)  # facing north
    for yaw in np.linspace(-3.1, 3.1, 13):
        assert yaw_ned_to_enu(yaw_enu_to_ned(yaw)) == pytest.approx(yaw)


def test_attitude_quaternion_both_ways() -> None:
    from scipy.spatial.transform import Rotation

    # level, nose north: FRD x = north = NED x, so PX4's quaternion is the identity
    R_north = Rotation.from_euler("z", 90, degrees=True).as_matrix()
    np.testing.assert_allclose(px4_quaternion(R_north), [1, 0, 0, 0], atol=1e-12)
    for R in Rotation.random(20, random_state=3).as_matrix():
        np.testing.assert_allclose(R_world_body_from_px4(px4_quaternion(R)), R, atol=1e-12)


def test_setpoint_through_px4_and_back() -> None:
    sp = Setpoint(0.0, np.array([1.0, -2.0, 3.0]), np.array([0.5, 0.2, -0.1]), np.array([0.1, 0.0, 0.3]),
                  np.array([0.0, 0.2, 0.0]), np.zeros(3), 0.4, -0.3)
    back = setpoint_from_px4(decode(encode(_outputs.px4_setpoint(sp, 10**9), "px4_msgs/msg/TrajectorySetpoint"),
                                    "px4_msgs/msg/TrajectorySetpoint"), 0.0)
    for name in ("position", "velocity", "acceleration", "jerk"):
        np.testing.assert_allclose(getattr(back, name), getattr(sp, name), atol=1e-6)
    assert (back.yaw, back.yaw_rate) == pytest.approx((sp.yaw, sp.yaw_rate), abs=1e-6)


def test_the_stream_flies_the_old_reference_until_the_new_one_starts() -> None:
    """A plan made for a time ahead (``plan_lead``) and handed over early: before its start the stream
    samples what it replaces, after it the new one, with no jump at the switch."""
    from mapkit.flight import Reference
    from mapkit.flight._pilot import brake
    from mapkit.flight._reference import YawFollower
    from mapkit.fly._stream import StreamedReference

    moving = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]])  # 1 m/s east
    old = Reference(brake(moving, 0.0, 3.0), YawFollower(lambda t: np.full(len(t), 1.0), 0.0, 0.0, 0.0, 3.0, 12.0, 9.0))
    start = 0.3
    new = Reference(brake(old.state(start), start, 1.0),  # a gentler brake from where the old one is then
                    YawFollower(lambda t: np.full(len(t), -1.0), start, float(old.yaw(start)[0]),
                                float(old.yaw_rate(start)[0]), 3.0, 12.0, 9.0))
    streamed = StreamedReference.of(new, start)
    streamed.previous = StreamedReference.of(old, 0.0)
    for t in (0.1, 0.25, 0.299):
        before, want = streamed.sample(t), old.sample(t)
        np.testing.assert_allclose(before.position, want.position, atol=1e-9)
        assert before.yaw == pytest.approx(want.yaw, abs=1e-3)
    a, b = streamed.sample(start - 1e-6), streamed.sample(start + 1e-6)
    np.testing.assert_allclose(a.position, b.position, atol=1e-5)
    np.testing.assert_allclose(a.velocity, b.velocity, atol=1e-4)
    assert a.yaw == pytest.approx(b.yaw, abs=1e-3) and a.yaw_rate == pytest.approx(b.yaw_rate, abs=0.05)
    np.testing.assert_allclose(streamed.sample(1.0).position, new.sample(1.0).position, atol=1e-9)
    assert streamed.sample(1.0).yaw == pytest.approx(float(new.yaw(1.0)[0]), abs=1e-3)
    with pytest.raises(FlyError, match=r"plan_lead 0\.5 s"):
        FlyConfig(plan_lead=0.5).validate()


def test_the_stream_takes_references_as_they_arrive_and_stops_when_told() -> None:
    """References sent while the stream waits for its next setpoint are taken then (the newest flown,
    what it replaces kept until its start); None stops the stream."""
    import multiprocessing as mp
    import threading
    from types import SimpleNamespace

    from mapkit.fly._stream import _receive_until

    stream_end, node_end = mp.Pipe()
    first, second = SimpleNamespace(name="first", previous=None), SimpleNamespace(name="second", previous=None)
    sender = threading.Timer(0.05, lambda: (node_end.send(first), node_end.send(second)))
    sender.start()
    reference, stop = _receive_until(stream_end, time.perf_counter() + 0.5, None)
    sender.join()
    assert not stop and reference.name == "second" and reference.previous.name == "first"
    node_end.send(None)
    assert _receive_until(stream_end, time.perf_counter() + 30.0, reference) == (reference, True)


def test_plans_lead_the_clock_by_their_measured_hand_over(pilot) -> None:
    """The configured lead until a few plans were handed over, then the median of the last twenty
    hand-over times plus 3 ms, at most half the pilot's replan interval."""
    from mapkit.fly import FlyNode

    cfg = FlyConfig(link=DdsConfig(domain_id=_domain()), plan_lead=0.08)
    node = FlyNode(pilot, cfg, _kept(Link(cfg.link)))
    node._handovers.extend([0.03] * 4)
    assert node.plan_lead == 0.08
    measured = [0.02] * 4 + [0.03] * 13 + [0.04, 0.05, 0.2]
    node._handovers.extend(measured)
    assert node.plan_lead == pytest.approx(0.03 + 0.003)
    node._handovers.extend([0.4] * 20)
    assert node.plan_lead == pytest.approx(0.5 * pilot.config.replan_interval)


def test_px4_odometry_to_enu() -> None:
    # 1 m north, 2 m east, 3 m up, nose east (NED yaw 90°), flying forward at 1 m/s in the body frame
    q = [math.cos(math.pi / 4), 0.0, 0.0, math.sin(math.pi / 4)]
    odo = _inputs.px4_odometry(message(
        "px4_msgs/msg/VehicleOdometry", timestamp=0, timestamp_sample=0, pose_frame=1,
        position=np.array([1.0, 2.0, -3.0], np.float32), q=np.array(q, np.float32), velocity_frame=3,
        velocity=np.array([1.0, 0.0, 0.0], np.float32), angular_velocity=np.zeros(3, np.float32),
        position_variance=np.zeros(3, np.float32), orientation_variance=np.zeros(3, np.float32),
        velocity_variance=np.zeros(3, np.float32), reset_counter=0, quality=0), 7)
    np.testing.assert_allclose(odo.position, [2.0, 1.0, 3.0], atol=1e-6)
    np.testing.assert_allclose(odo.velocity, [1.0, 0.0, 0.0], atol=1e-6)  # east
    assert odo.yaw == pytest.approx(0.0, abs=1e-6) and odo.stamp_ns == 7


def test_loopback_config_and_bad_values() -> None:
    xml = DdsConfig().xml()
    assert '<NetworkInterface name="lo"/>' in xml and "<AllowMulticast>false" in xml
    assert '<Peer address="localhost"/>' in xml
    with pytest.raises(FlyError, match="domain id 300"):
        DdsConfig(domain_id=300)
    with pytest.raises(FlyError, match="absolute ROS 2 topic"):
        FlyConfig(topics=_topics(depth="camera/depth")).validate()
    with pytest.raises(FlyError, match="2 Hz"):
        FlyConfig(rate=1.0).validate()


# -- the link ------------------------------------------------------------------------------------------------
def test_a_security_enclave_becomes_cyclones_security_section(tmp_path: Path) -> None:
    """An enclave as ``ros2 security create_enclave`` makes it: its six files in Cyclone's Security
    section; a missing one named; a Cyclone without security plugins refused in one line that says how
    to get one (the PyPI wheel has none)."""
    import xml.etree.ElementTree as ET

    from mapkit.fly._dds import ENCLAVE_FILES, has_security

    with pytest.raises(FlyError, match="is not a directory"):
        DdsConfig(enclave=str(tmp_path / "none"))
    for _, _, name in ENCLAVE_FILES[:-1]:
        (tmp_path / name).write_text("not a certificate")
    with pytest.raises(FlyError, match=r"has no permissions\.p7s; make it with `ros2 security create_enclave"):
        DdsConfig(enclave=str(tmp_path))
    (tmp_path / "permissions.p7s").write_text("not signed")
    config = DdsConfig(domain_id=_domain() - 60, enclave=str(tmp_path))  # a domain no other test opens
    ns = {"c": "https://cdds.io/config"}
    security = ET.fromstring(config.xml()).find("c:Domain/c:Security", ns)
    assert security is not None
    for section, element, name in ENCLAVE_FILES:
        assert security.find(f"c:{section}/c:{element}", ns).text == f"file:{tmp_path.resolve() / name}"
    assert ET.fromstring(DdsConfig().xml()).find("c:Domain/c:Security", ns) is None
    why = "ENABLE_SECURITY=ON" if not has_security() else "DDS Security refused enclave"
    with pytest.raises(FlyError, match=why):
        Link(config)


def test_messages_cross_between_processes_on_loopback(tmp_path: Path) -> None:
    domain = _domain()
    got: list[str] = []
    link = _kept(Link(DdsConfig(domain_id=domain)))
    link.reader("/chatter", "std_msgs/msg/String", lambda m, _: got.append(m.data), qos="reliable")
    code = ("import time; from mapkit.fly import Link, DdsConfig, message\n"
            f"link = Link(DdsConfig(domain_id={domain})); w = link.writer('/chatter', 'std_msgs/msg/String')\n"
            "end = time.time() + 20\n"
            "while link.matched('/chatter') == 0 and time.time() < end: time.sleep(0.05)\n"
            "for i in range(3): w(message('std_msgs/msg/String', data=f'hello {i}')); time.sleep(0.05)\n"
            "time.sleep(0.5)\n")
    subprocess.run([sys.executable, "-c", code], check=True, timeout=60)
    assert got == ["hello 0", "hello 1", "hello 2"]


def test_a_closed_link_leaves_its_peers_stops_its_callbacks_and_refuses_to_publish() -> None:
    domain = _domain()
    got: list[str] = []
    sender, receiver = _kept(Link(DdsConfig(domain_id=domain))), Link(DdsConfig(domain_id=domain))
    receiver.reader("/count", "std_msgs/msg/String", lambda m, _: got.append(m.data), qos="reliable")
    send, send_back = sender.writer("/count", "std_msgs/msg/String"), receiver.writer("/back", "std_msgs/msg/String")
    assert _wait(lambda: sender.matched("/count") == 1)
    send(message("std_msgs/msg/String", data="before"))
    assert _wait(lambda: got == ["before"], 5.0)
    receiver.close()
    assert _wait(lambda: sender.matched("/count") == 0, 5.0)  # the remote end saw it leave, without the GC
    send(message("std_msgs/msg/String", data="after"))
    time.sleep(0.3)
    assert got == ["before"]
    with pytest.raises(FlyError, match="link is closed; open a new Link to publish on /back"):
        send_back(message("std_msgs/msg/String", data="x"))
    with pytest.raises(FlyError, match="link is closed"):
        receiver.writer("/other", "std_msgs/msg/String")


# -- the node in this process, a publisher beside it -----------------------------------------------------------
@pytest.fixture(scope="module")
def pilot():
    from mapkit.flight import Pilot

    return Pilot.load("pretrained")


def _node(pilot, domain: int, **config):
    from mapkit.fly import FlyNode

    cfg = FlyConfig(link=DdsConfig(domain_id=domain), **config)
    node = FlyNode(pilot, cfg, _kept(Link(cfg.link)))
    node.start()
    return node


def _wait(predicate, timeout: float = 20.0) -> bool:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if predicate():
            return True
        time.sleep(0.02)
    return False


def _odometry(position, stamp_ns: int):
    p = message("geometry_msgs/msg/Point", x=float(position[0]), y=float(position[1]), z=float(position[2]))
    q = message("geometry_msgs/msg/Quaternion", x=0.0, y=0.0, z=0.0, w=1.0)
    v = message("geometry_msgs/msg/Vector3", x=0.0, y=0.0, z=0.0)
    return message("nav_msgs/msg/Odometry", header=_outputs.header(stamp_ns, "odom"), child_frame_id="base_link",
                   pose=message("geometry_msgs/msg/PoseWithCovariance",
                                pose=message("geometry_msgs/msg/Pose", position=p, orientation=q), covariance=np.zeros(36)),
                   twist=message("geometry_msgs/msg/TwistWithCovariance",
                                 twist=message("geometry_msgs/msg/Twist", linear=v, angular=v), covariance=np.zeros(36)))


def test_bad_messages_are_logged_once_per_kind_and_never_stop_the_node(pilot, caplog) -> None:
    domain = _domain() + 3
    node = _node(pilot, domain)
    try:
        link = _kept(Link(DdsConfig(domain_id=domain)))
        setpoints: list = []
        link.reader("/mapkit/setpoint", "trajectory_msgs/msg/MultiDOFJointTrajectory",
                    lambda m, _: setpoints.append(m.points[0].transforms[0].translation), qos="reliable")
        odometry = link.writer("/odom", "nav_msgs/msg/Odometry", qos="sensor")
        depth = link.writer("/camera/depth/image_rect_raw", "sensor_msgs/msg/Image", qos="sensor")
        goal = link.writer("/goal_pose", "geometry_msgs/msg/PoseStamped")
        assert _wait(lambda: link.matched("/odom") and link.matched("/camera/depth/image_rect_raw"))
        hdr = _outputs.header(time.time_ns(), "camera_optical")
        rgb = message("sensor_msgs/msg/Image", header=hdr, height=2, width=2, encoding="rgb8", is_bigendian=0,
                      step=6, data=np.zeros(12, np.uint8))
        cut = message("sensor_msgs/msg/Image", header=hdr, height=4, width=4, encoding="16UC1", is_bigendian=0,
                      step=8, data=np.zeros(10, np.uint8))
        for i in range(30):
            odometry(_odometry([0.0, 0.0, 1.0], time.time_ns()))
            if i == 2:
                goal(message("geometry_msgs/msg/PoseStamped", header=_outputs.header(time.time_ns(), "odom"),
                             pose=message("geometry_msgs/msg/Pose",
                                          position=message("geometry_msgs/msg/Point", x=5.0, y=0.0, z=1.0),
                                          orientation=message("geometry_msgs/msg/Quaternion", x=0.0, y=0.0, z=0.0, w=1.0))))
            depth(rgb if i % 2 else cut)
            time.sleep(0.02)
        assert _wait(lambda: node.log.counts.get("depth message", 0) >= 10)
        logged = [r for r in caplog.records if "encoding rgb8" in r.getMessage() or "corrupted" in r.getMessage()]
        assert 1 <= len(logged) <= 2  # one line per kind per 5 s, not one per message
        assert node.status["goal"] == [5.0, 0.0, 1.0] and all(t.is_alive() for t in node._threads)
        assert _wait(lambda: len(setpoints) > 5)  # it still streams: a hold, no frame has been flown
        p = setpoints[-1]
        np.testing.assert_allclose([p.x, p.y, p.z], [0.0, 0.0, 1.0], atol=1e-9)
    finally:
        node.close()


def test_a_goal_outside_the_geofence_is_refused_and_reported(pilot) -> None:
    domain = _domain() + 4
    node = _node(pilot, domain, fence_radius=10.0)
    try:
        link = _kept(Link(DdsConfig(domain_id=domain)))
        odometry = link.writer("/odom", "nav_msgs/msg/Odometry", qos="sensor")
        assert _wait(lambda: link.matched("/odom"))
        assert _wait(lambda: (odometry(_odometry([1.0, 2.0, 1.0], time.time_ns())) or
                              node.status["odometry_age"] is not None))
        assert "beyond the fence radius 10.0 m" in node.set_goal(np.array([12.0, 2.0, 1.0]))
        assert node.status["goal"] is None and node.status["refused_goal"] == [12.0, 2.0, 1.0]
        assert node.set_goal(np.array([9.0, 2.0, 1.0])) == ""
        assert "beyond ±5.0 m" in node.set_goal(np.array([1.0, 2.0, 7.0]))
    finally:
        node.close()


def test_a_recording_plays_back_as_live_topics_with_its_clock(tmp_path: Path) -> None:
    from mapkit.fly import Recording
    from mapkit.fly._replay import replay

    domain = _domain() + 5
    path = tmp_path / "chatter.mcap"
    recording = Recording(path)
    source = _kept(Link(DdsConfig(domain_id=domain), tap=recording.write))
    say = source.writer("/chatter", "std_msgs/msg/String")
    for i in range(5):
        say(message("std_msgs/msg/String", data=f"m{i}"))
        time.sleep(0.05)
    recording.close()
    heard: list[str] = []
    clock: list[int] = []
    listener = _kept(Link(DdsConfig(domain_id=domain)))
    listener.reader("/chatter", "std_msgs/msg/String", lambda m, _: heard.append(m.data), qos="reliable")
    listener.reader("/clock", "rosgraph_msgs/msg/Clock",
                    lambda m, _: clock.append(m.clock.sec * 10**9 + m.clock.nanosec), qos="reliable")
    player = _kept(Link(DdsConfig(domain_id=domain)))
    out = replay(path, player, rate=2.0, clock=True)
    assert _wait(lambda: len(heard) == 5, 5.0)
    assert heard == [f"m{i}" for i in range(5)] and out.topics == {"/chatter": 5}
    assert len(clock) == 5 and clock == sorted(clock) and 0.15e9 < clock[-1] - clock[0] < 0.5e9
    assert 0.08 < out.seconds < 0.5  # 0.2 s recorded, played at twice the pace
    with pytest.raises(FlyError, match="has no topic /nope"):
        replay(path, player, topics=["/nope"])


# -- software in the loop: `mapkit fly` in its own process, the vehicle here ------------------------------------
ISOLATED = "MAPKIT_SITL_ISOLATED"
"""Set by :func:`test_software_in_the_loop_in_a_fresh_interpreter`: the flights below run only in an
interpreter of their own. In a test worker that earlier tests left with DDS participants, Cyclone
entities torn down by the garbage collector mid-flight disturbed them (and once crashed the worker)."""
sitl = pytest.mark.skipif(not os.environ.get(ISOLATED), reason="run by test_software_in_the_loop_in_a_fresh_interpreter")


@pytest.mark.slow
def test_software_in_the_loop_in_a_fresh_interpreter() -> None:
    env = {**os.environ, ISOLATED: "1", "PYTHONFAULTHANDLER": "1"}  # a crash prints where it happened
    env.pop("PYTEST_XDIST_WORKER", None)
    proc = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-p", "no:xdist",
                           str(Path(__file__)), "-k", "pillar or lost"], env=env, capture_output=True, text=True,
                          timeout=900)
    assert proc.returncode == 0 and "3 passed" in proc.stdout, proc.stdout[-3000:] + proc.stderr[-3000:]


def _pillar_world():
    """A hall (floor, ceiling at 3.5 m) with a pillar on the straight line from (0, 0, 1.5) to (8, 0, 1.5)."""
    from mapkit.sim import Cylinder, HalfSpace, World

    return World([HalfSpace((0.0, 0.0, 1.0), 0.0), HalfSpace((0.0, 0.0, -1.0), -3.5),
                  Cylinder((4.0, 0.0, 0.0), (4.0, 0.0, 3.5), 0.4)], np.array([[-5.0, -8.0, 0.0], [13.0, 8.0, 3.5]]))


def _start_node(domain: int, *extra: str) -> subprocess.Popen[str]:
    args = [sys.executable, "-m", "mapkit.cli", "fly", "--sim-time", "--domain-id", str(domain), *extra]
    return subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)


def _interrupt(node: subprocess.Popen[str]) -> str:
    """Ctrl-C the node; its output. A node that does not stop within 60 s is killed, and that fails."""
    node.send_signal(signal.SIGINT)
    try:
        return node.communicate(timeout=60)[0]
    except subprocess.TimeoutExpired:
        node.kill()
        out = node.communicate()[0]
        raise AssertionError(f"mapkit fly did not stop on Ctrl-C within 60 s:\n{out[-3000:]}") from None


def _vehicle(domain: int, odometry: str = "nav_msgs"):
    from mapkit.flight._recorded import load_network
    from mapkit.fly import SimulatedVehicle, Topics

    _, camera = load_network("pretrained")
    statuses: list[dict] = []
    link = _kept(Link(DdsConfig(domain_id=domain)))
    link.reader("/mapkit/status", "std_msgs/msg/String", lambda m, _: statuses.append(json.loads(m.data)), qos="reliable")
    vehicle = SimulatedVehicle(link, _pillar_world(), camera, FlyConfig(topics=Topics(odometry_type=odometry)))
    assert vehicle.wait_for_node(60), "the node did not appear on the loopback domain"
    return vehicle, statuses


@sitl
def test_the_node_flies_a_simulated_vehicle_around_a_pillar_and_records_it(tmp_path: Path) -> None:
    domain = _domain() + 1
    record = tmp_path / "flight.mcap"
    node = _start_node(domain, "--record", str(record))
    try:
        vehicle, statuses = _vehicle(domain)
        flight = vehicle.fly(np.array([0.0, 0.0, 1.5]), np.array([8.0, 0.0, 1.5]), time_limit=20.0)
        assert flight.outcome == "success", (flight, statuses[-1:] if statuses else None)
        assert flight.min_distance > 0.3 and flight.setpoints > 100
        assert max(abs(flight.path[:, 3] - 1.5)) < 1.0 < max(abs(flight.path[:, 2]))  # around the pillar
    finally:
        out = _interrupt(node)
    assert node.returncode == 130, out
    from mapkit.ingest import inspect_recordings

    (info,) = inspect_recordings([record])
    topics = set(info.summary.topics)
    assert {"/camera/depth/image_rect_raw", "/odom", "/fmu/in/trajectory_setpoint", "/mapkit/path"} <= topics


@sitl
@pytest.mark.parametrize("lost", ["depth", "odometry"])
def test_an_input_lost_mid_flight_brakes_to_rest_and_holds(lost: str) -> None:
    """With PX4's odometry (NED in, NED setpoints out): depth or odometry stops 1.5 s into the flight."""
    domain = _domain() + (2 if lost == "depth" else 6)
    node = _start_node(domain, "--set", "pilot.frame_timeout=0.3", "--odometry", "px4")
    try:
        vehicle, statuses = _vehicle(domain, odometry="px4")
        vehicle.fault, vehicle.fault_after = lost, 1.5
        flight = vehicle.fly(np.array([0.0, 0.0, 1.5]), np.array([8.0, 0.0, 1.5]), time_limit=6.0)
    finally:
        _interrupt(node)
    assert flight.outcome == "timeout"  # it stopped short of the pillar and the goal
    t, x = flight.path[:, 0], flight.path[:, 1:]
    speed = np.linalg.norm(np.diff(x, axis=0), axis=1) / np.diff(t)
    assert speed[t[1:] < t[0] + 1.5].max() > 0.5  # it was flying
    assert speed[t[1:] > t[-1] - 1.0].max() < 0.1  # and is at rest by the end
    assert flight.min_distance > 0.3
    why = "no depth frame" if lost == "depth" else "no odometry"
    assert any(s["state"] in ("braking", "blocked") and why in s["reason"] for s in statuses)


# -- helpers -----------------------------------------------------------------------------------------------
def _topics(**kw: str):
    from mapkit.fly import Topics

    return Topics(**kw)


def _example(msgtype: str):
    hdr = _outputs.header(1_500_000_123, "odom")
    if msgtype == "sensor_msgs/msg/Image":
        return message(msgtype, header=hdr, height=2, width=3, encoding="16UC1", is_bigendian=0, step=6,
                       data=np.arange(12, dtype=np.uint8))
    if msgtype == "px4_msgs/msg/TrajectorySetpoint":
        sp = Setpoint(0.0, np.ones(3), np.zeros(3), np.zeros(3), np.zeros(3), np.zeros(3), 0.1, 0.2)
        return _outputs.px4_setpoint(sp, 10**9)
    if msgtype == "trajectory_msgs/msg/MultiDOFJointTrajectory":
        sp = Setpoint(0.0, np.ones(3), np.ones(3), np.zeros(3), np.zeros(3), np.zeros(3), 0.1, 0.2)
        return _outputs.multidof_setpoint(sp, 10**9, "odom", "base_link")
    if msgtype == "tf2_msgs/msg/TFMessage":
        return message(msgtype, transforms=[])
    from mapkit.flight import Reference

    return _outputs.path(Reference.holding(np.zeros(3), 0.0, 0.0), 0.0, 10**9, "odom")
