"""A DDS participant speaking ROS 2 topics, with no ROS installation (Eclipse Cyclone DDS).

ROS 2 puts topic ``/a/b`` on DDS topic ``rt/a/b`` with type ``pkg::msg::dds_::Name_``; ROS 2 nodes on
Cyclone DDS or Fast DDS (PX4's uXRCE-DDS agent) match these readers and writers over RTPS. By default
the participant uses the loopback interface only, with multicast off and localhost as its only peer:
nothing is sent to any other address. Another interface is used only when named.
"""

from __future__ import annotations

import atexit
import ctypes.util
import threading
import time
import weakref
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal
from xml.sax.saxutils import escape, quoteattr

from mapkit.fly._errors import FlyError
from mapkit.fly._msgs import dds_type, decode, encode

Tap = Callable[[str, str, bytes, int], None]
QosName = Literal["sensor", "reliable", "latched"]
QOS_NAMES: tuple[str, ...] = ("sensor", "reliable", "latched")
LOOPBACK = "lo"
ENCLAVE_FILES = (("Authentication", "IdentityCertificate", "cert.pem"),
                 ("Authentication", "IdentityCA", "identity_ca.cert.pem"),
                 ("Authentication", "PrivateKey", "key.pem"),
                 ("AccessControl", "PermissionsCA", "permissions_ca.cert.pem"),
                 ("AccessControl", "Governance", "governance.p7s"),
                 ("AccessControl", "Permissions", "permissions.p7s"))
"""(section, Cyclone's element, the file of a ROS 2 security enclave) for each DDS Security file, as
ROS 2's middleware reads an enclave made by ``ros2 security create_enclave``."""
SECURITY_BUILD = ("DDS Security needs a Cyclone DDS built with it, and this one has none (the PyPI wheel is built "
                  "without): build Cyclone DDS with -DENABLE_SECURITY=ON and install its Python binding against it "
                  "(CYCLONEDDS_HOME=<its install> pip install --no-binary cyclonedds cyclonedds)")


@dataclass(frozen=True)
class DdsConfig:
    """Where the participant talks."""

    domain_id: int = 0
    """The ROS domain id (ROS_DOMAIN_ID): 0–232."""
    interface: str = LOOPBACK
    """Network interface to use. ``lo``: loopback only, unicast to localhost. Another name (``eth0``,
    ``wlan0``) joins that network with ROS 2's usual multicast discovery."""
    peers: tuple[str, ...] = ()
    """Extra unicast discovery peers (addresses), for networks without multicast."""
    enclave: str = ""
    """A ROS 2 security enclave: the directory ``ros2 security create_enclave KEYSTORE NAME`` makes (its
    certificate and key, the two CAs, the signed governance and permissions). The participant then
    authenticates, encrypts and keeps to its permissions with DDS Security, as a ROS 2 node run with that
    enclave and ROS_SECURITY_ENABLE=true. Empty: no security. Needs a Cyclone DDS built with security."""

    def __post_init__(self) -> None:
        if not 0 <= self.domain_id <= 232:
            raise FlyError(f"domain id {self.domain_id} is outside ROS 2's 0–232; pass --domain-id in that range")
        if not self.interface or any(c in self.interface for c in "<>&\"'"):
            raise FlyError(f"interface {self.interface!r} is not an interface name; pass e.g. --interface eth0")
        if self.enclave and not Path(self.enclave).is_dir():
            raise FlyError(f"enclave {self.enclave} is not a directory; make one with `ros2 security create_enclave "
                           "KEYSTORE /mapkit` and pass KEYSTORE/enclaves/mapkit")
        missing = [name for _, _, name in ENCLAVE_FILES if self.enclave and not (Path(self.enclave) / name).is_file()]
        if missing:
            raise FlyError(f"enclave {self.enclave} has no {', '.join(missing)}; make it with `ros2 security "
                           "create_enclave KEYSTORE /mapkit` and pass KEYSTORE/enclaves/mapkit")

    def xml(self) -> str:
        """The Cyclone DDS configuration of this participant."""
        loopback = self.interface == LOOPBACK
        peers = ("localhost", *self.peers) if loopback else self.peers
        peer_xml = "".join(f"<Peer address={quoteattr(p)}/>" for p in peers)
        return (
            '<CycloneDDS xmlns="https://cdds.io/config"><Domain Id="any"><General>'
            f"<Interfaces><NetworkInterface name={quoteattr(self.interface)}/></Interfaces>"
            f"<AllowMulticast>{'false' if loopback else 'default'}</AllowMulticast></General>"
            "<Discovery><ParticipantIndex>auto</ParticipantIndex><MaxAutoParticipantIndex>60</MaxAutoParticipantIndex>"
            f"{'<Peers>' + peer_xml + '</Peers>' if peer_xml else ''}</Discovery>{self._security_xml()}"
            "</Domain></CycloneDDS>"
        )

    def _security_xml(self) -> str:
        """Cyclone's Security section for :attr:`enclave` ('' without one)."""
        if not self.enclave:
            return ""
        root = Path(self.enclave).resolve()
        sections: dict[str, str] = {}
        for section, element, name in ENCLAVE_FILES:
            sections[section] = sections.get(section, "") + f"<{element}>{escape('file:' + str(root / name))}</{element}>"
        return "<Security>" + "".join(f"<{k}>{v}</{k}>" for k, v in sections.items()) + "</Security>"


def has_security() -> bool:
    """True when Cyclone DDS's security plugins are here (a build with ENABLE_SECURITY installs them
    beside its library; the PyPI wheel has none)."""
    from cyclonedds.__library__ import library_path

    beside = any(Path(library_path).parent.glob("*dds_security_auth*"))
    return beside or ctypes.util.find_library("dds_security_auth") is not None


def _refused(config: DdsConfig, exc: Exception) -> FlyError:
    """Why Cyclone refused to start the participant, and the fix, as one line."""
    if config.enclave and not has_security():
        return FlyError(f"enclave {config.enclave}: {SECURITY_BUILD}")
    if config.enclave:
        return FlyError(f"DDS Security refused enclave {config.enclave} ({exc}): check that its certificate is "
                        f"signed by its identity CA and that its permissions allow domain {config.domain_id}")
    return FlyError(f"DDS cannot start on interface {config.interface!r} (domain {config.domain_id}): {exc}; "
                    "check the interface name (`ip link`)")


def dds_topic(name: str) -> str:
    """The DDS topic of ROS 2 topic `name`: ``/camera/depth`` → ``rt/camera/depth``."""
    if not name.startswith("/") or name.endswith("/") or "//" in name:
        raise FlyError(f"topic {name!r} is not an absolute ROS 2 topic name; write it as /namespace/name")
    return "rt" + name


def _qos(name: str) -> Any:
    from cyclonedds.qos import Policy, Qos

    if name == "sensor":  # ROS 2's SensorDataQoS
        return Qos(Policy.Reliability.BestEffort, Policy.History.KeepLast(5), Policy.Durability.Volatile)
    if name == "reliable":
        return Qos(Policy.Reliability.Reliable(max_blocking_time=0), Policy.History.KeepLast(10),
                   Policy.Durability.Volatile)
    if name == "latched":  # tf_static
        return Qos(Policy.Reliability.Reliable(max_blocking_time=0), Policy.History.KeepLast(1),
                   Policy.Durability.TransientLocal)
    raise FlyError(f"QoS {name!r} is unknown; use one of {', '.join(QOS_NAMES)}")


_DOMAINS: dict[int, tuple[str, Any]] = {}
_DOMAINS_LOCK = threading.Lock()
_OPEN_LINKS: weakref.WeakSet[Link] = weakref.WeakSet()


def _domain(config: DdsConfig) -> None:
    """Creates the process's Cyclone domain with this configuration (once per domain id)."""
    from cyclonedds.domain import Domain

    xml = config.xml()
    with _DOMAINS_LOCK:
        if config.domain_id in _DOMAINS:
            if _DOMAINS[config.domain_id][0] != xml:
                raise FlyError(f"domain {config.domain_id} is already open here with another interface; "
                               "use one DdsConfig per domain in a process")
            return
        try:
            _DOMAINS[config.domain_id] = (xml, Domain(config.domain_id, xml))
        except Exception as exc:  # Cyclone raises DDSException with a generic text for a bad config
            raise _refused(config, exc) from exc


class Link:
    """One DDS participant: ROS 2 topic readers (callbacks with decoded messages) and writers."""

    def __init__(self, config: DdsConfig | None = None, *, tap: Tap | None = None) -> None:
        from cyclonedds.domain import DomainParticipant

        self.config = config or DdsConfig()
        self.tap = tap
        """Called with (topic, msgtype, CDR bytes, time ns) for every message read or written."""
        _domain(self.config)
        try:
            self._participant: Any = DomainParticipant(self.config.domain_id)
        except Exception as exc:  # security plugins check the enclave when a participant starts
            raise _refused(self.config, exc) from exc
        self._topics: dict[str, Any] = {}
        self._entities: list[Any] = []
        _OPEN_LINKS.add(self)

    def _topic(self, name: str, msgtype: str) -> Any:
        from cyclonedds.topic import Topic

        key = dds_topic(name)
        if self._participant is None:
            raise FlyError(f"the link is closed; open a new Link to use {name}")
        if key not in self._topics:
            self._topics[key] = Topic(self._participant, key, dds_type(msgtype))
        return self._topics[key]

    def writer(self, topic: str, msgtype: str, qos: str = "reliable") -> Callable[[Any], None]:
        """A function that publishes one rosbags message object of `msgtype` on ROS 2 `topic`."""
        write = self.raw_writer(topic, msgtype, qos)
        return lambda msg: write(encode(msg, msgtype))

    def raw_writer(self, topic: str, msgtype: str, qos: str = "reliable") -> Callable[[bytes], None]:
        """A function that publishes CDR bytes (a recorded message as it is) of `msgtype` on `topic`."""
        from cyclonedds.pub import DataWriter

        w = DataWriter(self._participant, self._topic(topic, msgtype), qos=_qos(qos))
        self._entities.append(w)
        kind = dds_type(msgtype)

        def write(raw: bytes) -> None:
            if self._participant is None:
                raise FlyError(f"the link is closed; open a new Link to publish on {topic}")
            if self.tap is not None:
                self.tap(topic, msgtype, raw, time.time_ns())
            w.write(kind.deserialize(raw))

        return write

    def reader(self, topic: str, msgtype: str, on_message: Callable[[Any, int], None], *,
               qos: str = "sensor", on_error: Callable[[str, Exception], None] | None = None) -> None:
        """Calls ``on_message(msg, received_ns)`` for each message on `topic` (on Cyclone's thread).

        A message that does not decode, or that ``on_message`` refuses by raising, goes to
        ``on_error(topic, exc)`` instead, never up Cyclone's thread."""
        from cyclonedds.core import Listener
        from cyclonedds.sub import DataReader

        def report(exc: Exception) -> None:
            if on_error is not None:
                on_error(topic, exc)

        def on_data_available(reader: Any) -> None:
            try:
                samples = reader.take(N=64)
            except Exception as exc:  # noqa: BLE001 - bytes that are not this type: reported, the link goes on
                report(exc)
                return
            for sample in samples:
                if not hasattr(sample, "cdr"):  # an InvalidSample: a writer left (the instance's state changed)
                    continue
                received_ns = time.time_ns()
                try:
                    raw = sample.serialize()
                    if self.tap is not None:
                        self.tap(topic, msgtype, raw, received_ns)
                    on_message(decode(raw, msgtype), received_ns)
                except Exception as exc:  # noqa: BLE001 - a message the node cannot use: reported, never up Cyclone's thread
                    report(exc)

        r = DataReader(self._participant, self._topic(topic, msgtype), qos=_qos(qos),
                       listener=Listener(on_data_available=on_data_available))
        self._entities.append(r)

    def matched(self, topic: str) -> int:
        """How many remote readers or writers this participant's entities on ROS 2 `topic` match now."""
        name = dds_topic(topic)
        return sum(
            len(e.get_matched_subscriptions() if hasattr(e, "write") else e.get_matched_publications())
            for e in self._entities
            if e.topic.name == name
        )

    def close(self) -> None:
        """Deletes the participant and everything it made (remote ends see them leave). Its readers'
        callbacks are not called after this returns."""
        participant, self._participant = self._participant, None
        self._entities.clear()
        self._topics.clear()
        if participant is not None:
            # cyclonedds-python deletes entities only from __del__; called now, the C side (readers,
            # writers, topics, their listener threads) is gone before this returns, not whenever the GC runs
            participant.__del__()


@atexit.register
def _close_all() -> None:
    """Deletes every open participant and domain before the interpreter finalizes: a listener thread
    calling into a finalizing interpreter crashes the process at exit (seen as SIGSEGV)."""
    for link in list(_OPEN_LINKS):
        link.close()
    with _DOMAINS_LOCK:
        domains = [domain for _, domain in _DOMAINS.values()]
        _DOMAINS.clear()
    for domain in domains:
        domain.__del__()
