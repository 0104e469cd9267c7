"""Recordings → a stream of synchronised depth frames with camera and body poses."""

from __future__ import annotations

import logging
from collections import Counter, deque
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from mapkit._threads import prefetch
from mapkit.geometry import transform_from_pose
from mapkit.ingest._decode import (
    ACCEPTED,
    CAMERA_INFO_TYPE,
    IMAGE_TYPES,
    POSE_TYPES,
    READABLE_ENCODINGS,
    TF_TYPE,
    camera_intrinsics,
    decode_depth,
    frame_name,
    image_encoding,
    pose_sample,
    stamp_ns,
    tf_samples,
)
from mapkit.ingest._errors import IngestError
from mapkit.ingest._fastcdr import parse_image, parse_odometry
from mapkit.ingest._sources import BagSummary, Source, normalize_topic
from mapkit.ingest._tf import NO_POSE, POSE_GAP, EdgeSeries, NoPose, TfTree

log = logging.getLogger(__name__)

NO_VALID_DEPTH = "no_valid_depth"
NON_MONOTONIC = "non_monotonic_stamp"


@dataclass
class IngestConfig:
    """How recordings are read: the ``ingest`` settings of every command that reads recordings (`mapkit config ingest`)."""

    depth_topic: str | None = None
    """Depth image topic; auto-detected from message type and encoding when None."""
    camera_info_topic: str | None = None
    """CameraInfo topic; auto-detected (same namespace as the depth topic preferred) when None."""
    pose_topic: str | None = None
    """Odometry / PoseStamped / PoseWithCovarianceStamped topic, or 'tf' to use the tf tree only."""
    world_frame: str | None = None
    """Fixed frame of the output poses; the pose topic's frame (or the tf root) when None."""
    camera_frame: str | None = None
    """Optical frame of the depth camera; the depth images' header.frame_id when None."""
    body_frame: str | None = None
    """Body frame; the Odometry child frame, or the frame where the static chain to the camera starts."""
    intrinsics: NDArray[np.float64] | None = None
    """3x3 K used instead of (or when there is no) CameraInfo."""
    extrinsic: NDArray[np.float64] | None = None
    """T_body_camera (optical) overriding tf_static."""
    max_pose_gap: float = 0.1
    """Seconds; a depth frame between two pose samples further apart than this is dropped."""
    stride: int = 1
    """Keep every stride-th depth message."""
    max_frames: int | None = None
    """Stop after this many frames (over all inputs)."""
    drop_nonmonotonic: bool = False
    """Drop (and count) depth or pose messages whose stamp goes backwards instead of failing."""

    def validate(self) -> None:
        if not self.max_pose_gap > 0:
            raise IngestError(f"max_pose_gap {self.max_pose_gap} must be positive (seconds)")
        if self.stride < 1:
            raise IngestError(f"stride {self.stride} must be at least 1")
        if self.max_frames is not None and self.max_frames < 1:
            raise IngestError(f"max_frames {self.max_frames} must be at least 1")

    def to_attrs(self) -> dict[str, Any]:
        return {key: value.tolist() if isinstance(value, np.ndarray) else value for key, value in self.__dict__.items()}


@dataclass(frozen=True)
class Frame:
    """One synchronised depth frame."""

    depth: NDArray[np.float32]
    """(H, W) metres along the optical axis, NaN invalid."""
    stamp_ns: int
    T_world_camera: NDArray[np.float64]
    """(4, 4) camera optical frame → world."""
    T_world_body: NDArray[np.float64]
    """(4, 4) body frame → world."""
    K: NDArray[np.float64]
    """(3, 3) pinhole intrinsics; pixel (u, v) integer at the pixel centre."""
    source_index: int
    """Index of the input recording."""


@dataclass(frozen=True)
class RoleChoice:
    """The topic picked for one role of a recording (camera info or pose), and why."""

    topic: str | None
    """None: the role is filled otherwise (camera info: ``--intrinsics``; pose: the tf tree)."""
    msgtype: str | None
    why: str


@dataclass(frozen=True)
class DepthChoice:
    """The depth topic of a recording, and why it was picked."""

    topic: str
    msgtype: str
    why: str


@dataclass(frozen=True)
class Roles:
    """Which topics of one recording give depth, camera info, poses and tf (:func:`choose_roles`)."""

    summary: BagSummary
    depth: DepthChoice
    depth_encoding: str
    camera_info: RoleChoice
    pose: RoleChoice
    tf_topics: list[str]


@dataclass(frozen=True)
class SourcePlan(Roles):
    """What will be read from one recording and why: the roles plus the intrinsics and frames they
    resolve to (:func:`plan_source`)."""

    K: NDArray[np.float64]
    """(3, 3) intrinsics: ``--intrinsics`` or the camera info's."""
    width: int
    """Image size from the camera info; 0 when ``--intrinsics`` replaced it (the images then say)."""
    height: int
    world_frame: str
    body_frame: str
    camera_frame: str
    pose_parent: str
    """The frame the pose topic's poses are in ("" without a pose topic)."""
    needs_dynamic_tf: bool
    """True when /tf must be read while streaming (no pose topic, or another moving frame on the chain)."""


def _find(summary: BagSummary, name: str, option: str) -> str:
    """The normalised topic ``name`` given by ``option``; raises when the recording lacks it."""
    topic = normalize_topic(name)
    if topic not in summary.topics:
        raise IngestError(f"{option} {name}: no such topic in {str(summary.path)!r}; it has "
                          + ", ".join(sorted(summary.topics)))
    return topic


class _EmptyTopic(IngestError):
    """A listed topic without messages (not damage)."""


def _first_message(source: Source, topic: str) -> Any:
    """The first message of ``topic``, deserialised; raises :class:`_EmptyTopic` when there is none."""
    for raw in source.messages([topic]):
        return source.deserialize(raw)
    raise _EmptyTopic(f"topic {topic} in {str(source.path)!r} has no messages")


def plan_source(source: Source, config: IngestConfig) -> SourcePlan:
    """The whole reading plan of one recording: its roles, then the intrinsics and frames they resolve to."""
    return _resolve(source, choose_roles(source, config), config)


def choose_roles(source: Source, config: IngestConfig) -> Roles:
    """Pick the depth, camera-info and pose topics of one recording (overrides first)."""
    s = source.summary
    by_type: dict[str, list[str]] = {}
    for t in s.topics.values():
        by_type.setdefault(t.msgtype, []).append(t.name)
    depth = _choose_depth(source, config, by_type)
    depth_encoding = image_encoding(_first_message(source, depth.topic), depth.msgtype)
    camera_info = _choose_camera_info(s, config, by_type, depth.topic)
    tf_topics = sorted(by_type.get(TF_TYPE, []))
    pose = _choose_pose(s, config, by_type, tf_topics)
    return Roles(s, depth, depth_encoding, camera_info, pose, tf_topics)


def _choose_depth(source: Source, config: IngestConfig, by_type: dict[str, list[str]]) -> DepthChoice:
    """Depth: the given topic, else an Image with a depth encoding or a compressedDepth CompressedImage."""
    s = source.summary
    if config.depth_topic:
        topic = _find(s, config.depth_topic, "--depth-topic")
        msgtype = s.topics[topic].msgtype
        if msgtype not in IMAGE_TYPES:
            raise IngestError(f"--depth-topic {topic} carries {msgtype}; expected sensor_msgs/Image or CompressedImage")
        enc = image_encoding(_first_message(source, topic), msgtype)
        if enc not in READABLE_ENCODINGS:
            raise IngestError(f"topic {topic} has encoding {enc}; expected {ACCEPTED}; pass --depth-topic")
        return DepthChoice(topic, msgtype, "given by --depth-topic")
    images = [t for mt in IMAGE_TYPES for t in by_type.get(mt, [])]
    seen: list[str] = []
    unreadable: list[str] = []
    candidates: list[tuple[tuple[bool, bool, int], str, str, str]] = []
    for topic in images:
        msgtype = s.topics[topic].msgtype
        try:
            enc = image_encoding(_first_message(source, topic), msgtype)
        except _EmptyTopic:
            continue
        except IngestError as exc:
            unreadable.append(str(exc))
            continue
        seen.append(f"{topic} ({enc})")
        if enc in READABLE_ENCODINGS:
            # Prefer names that say depth, raw over compressed, then the busiest topic.
            rank = ("depth" in topic.lower(), msgtype.endswith("/Image"), s.topics[topic].count)
            candidates.append((rank, topic, msgtype, enc))
    if not candidates and unreadable:
        raise IngestError(f"{str(s.path)!r} lists image topics but cannot give their messages, so it is damaged "
                          f"({unreadable[0]})")
    if not candidates:
        listed = ", ".join(seen) if seen else "none"
        raise IngestError(f"no depth topic in {str(s.path)!r}: image topics seen: {listed}; expected encoding "
                          f"{ACCEPTED}; pass --depth-topic")
    candidates.sort(reverse=True)
    _, topic, msgtype, enc = candidates[0]
    others = [c[1] for c in candidates[1:]]
    why = f"{msgtype.split('/')[-1]} with encoding {enc}"
    if others:
        why += f"; preferred over {', '.join(others)} (name/type/count)"
    return DepthChoice(topic, msgtype, why)


def _choose_camera_info(s: BagSummary, config: IngestConfig, by_type: dict[str, list[str]], depth_topic: str) -> RoleChoice:
    """Camera info: the given one, else the CameraInfo sharing the depth topic's namespace."""
    infos = by_type.get(CAMERA_INFO_TYPE, [])
    if config.camera_info_topic:
        topic = _find(s, config.camera_info_topic, "ingest.camera_info_topic")
        return RoleChoice(topic, CAMERA_INFO_TYPE, "given by ingest.camera_info_topic")
    if config.intrinsics is not None:
        return RoleChoice(None, None, "--intrinsics given")
    if infos:
        base = depth_topic.rsplit("/", 1)[0]
        infos.sort(key=lambda t: (not t.startswith(base + "/"), "depth" not in t.lower(), t))
        why = "CameraInfo in the depth topic's namespace" if infos[0].startswith(base + "/") else "only CameraInfo topic" if len(infos) == 1 else "CameraInfo whose name says depth"
        return RoleChoice(infos[0], CAMERA_INFO_TYPE, why)
    raise IngestError(f"no camera info in {str(s.path)!r} (no sensor_msgs/CameraInfo topic); "
                      "pass --intrinsics fx,fy,cx,cy")


def _choose_pose(s: BagSummary, config: IngestConfig, by_type: dict[str, list[str]], tf_topics: list[str]) -> RoleChoice:
    """Pose: the given topic, else an Odometry, else a PoseStamped/-WithCovariance, else tf."""
    if config.pose_topic and config.pose_topic.strip().lower() != "tf":
        topic = _find(s, config.pose_topic, "--pose-topic")
        msgtype = s.topics[topic].msgtype
        if msgtype not in POSE_TYPES:
            raise IngestError(f"--pose-topic {topic} carries {msgtype}; expected nav_msgs/Odometry, "
                              "geometry_msgs/PoseStamped, PoseWithCovarianceStamped or TransformStamped (or 'tf')")
        return RoleChoice(topic, msgtype, "given by --pose-topic")
    poses = [(mt, t) for mt in POSE_TYPES for t in by_type.get(mt, [])]
    if poses and not config.pose_topic:
        mt, topic = poses[0]
        same = [t for m, t in poses if m == mt]
        if len(same) > 1:
            topic = max(same, key=lambda t: s.topics[t].count)
        return RoleChoice(topic, mt, f"{mt.split('/')[-1]} topic" + (f"; preferred over {len(poses) - 1} other pose topic(s)" if len(poses) > 1 else ""))
    if any(s.topics[t].count for t in tf_topics if "static" not in t):
        return RoleChoice(None, TF_TYPE, "no pose topic; world → camera from the tf tree")
    raise IngestError(f"no pose in {str(s.path)!r}: no Odometry/PoseStamped topic and no /tf; "
                      "record one or pass --pose-topic")


class _PoseFeed:
    """Turns pose, tf and tf_static messages into a TfTree as a recording streams by."""

    def __init__(self, pose_topic: str | None, tf_topics: list[str], config: IngestConfig) -> None:
        self.pose_topic, self.config = pose_topic, config
        self.topics = tf_topics + ([pose_topic] if pose_topic else [])  # what to read: these tf topics + the pose topic
        self.tree = TfTree()
        self.pose_series: EdgeSeries | None = None
        self._last_pose_stamp: int | None = None
        self.dropped_poses = 0

    @classmethod
    def for_plan(cls, plan: SourcePlan, config: IngestConfig) -> _PoseFeed:
        """A feed for streaming a planned recording: the pose topic pinned to world → body, the
        ``extrinsic`` pinned to body → camera, /tf only when the plan needs it."""
        tf = [t for t in plan.tf_topics if plan.needs_dynamic_tf or "static" in t]
        feed = cls(plan.pose.topic, tf, config)
        body = plan.body_frame
        if plan.pose.topic:
            # The pose topic defines world → body; tf's say about that edge is ignored.
            feed.pose_series = EdgeSeries(plan.pose_parent, body, f"pose topic {plan.pose.topic}")
            feed.tree.replace_dynamic(feed.pose_series)
            feed.tree.pinned.add(body)
        if config.extrinsic is not None and body != plan.camera_frame:
            feed.tree.set_static(body, plan.camera_frame, np.asarray(config.extrinsic, dtype=np.float64))
            feed.tree.pinned.add(plan.camera_frame)
        return feed

    def add(self, topic: str, msgtype: str, msg: Any) -> None:
        """One message of the pose topic or a tf topic."""
        if topic == self.pose_topic:
            self.add_pose(topic, *pose_sample(msg, msgtype))
            return
        static = "static" in topic
        for stamp, parent, child, t, q in tf_samples(msg):
            if static:
                self.tree.set_static(parent, child, transform_from_pose(t, q))
            else:
                self.tree.add_dynamic(parent, child, stamp, t, q, f"topic {topic}")

    def add_pose(self, topic: str, stamp: int, parent: str, child: str | None, t: NDArray[np.float64],
                 q: NDArray[np.float64]) -> None:
        """One sample of the pose topic (parent → child frame)."""
        last = self._last_pose_stamp
        if last is not None and stamp < last:
            if not self.config.drop_nonmonotonic:
                raise IngestError(f"pose topic {topic}: stamp goes backwards ({stamp} ns after {last} ns); fix the "
                                  "recording's clock or pass --set ingest.drop_nonmonotonic=true to drop such messages")
            self.dropped_poses += 1
            return
        self._last_pose_stamp = stamp
        if self.pose_series is None:  # planning: the body frame is not known yet
            self.pose_series = EdgeSeries(parent, child or "", f"pose topic {topic}")
        self.pose_series.add(stamp, t, q)


def _resolve(source: Source, roles: Roles, config: IngestConfig) -> SourcePlan:
    """Resolve intrinsics and the world / body / camera frames from the first seconds of a recording."""
    first = _first_message(source, roles.depth.topic)
    camera = frame_name(config.camera_frame or first.header.frame_id)
    if not camera:
        raise IngestError(f"depth topic {roles.depth.topic} has an empty header.frame_id; set ingest.camera_frame")
    feed, info_msg = _read_until_planned(source, roles, config, camera)
    K, width, height = _intrinsics(roles, config, info_msg)
    tree, pose_series = feed.tree, feed.pose_series
    if pose_series is not None:
        body = _body_of_pose_topic(roles, config, tree, pose_series, camera)
        pose_parent = pose_series.parent
        pose_series.child = body
        tree.replace_dynamic(pose_series)
        world = frame_name(config.world_frame or pose_series.parent)
    else:
        if camera not in tree.frames:
            raise IngestError(
                f"camera frame {camera!r} is not in the tf tree (frames: {', '.join(sorted(tree.frames)) or 'none'}); "
                "pass --set ingest.camera_frame=NAME or --pose-topic"
            )
        pose_parent = ""
        world = frame_name(config.world_frame or tree.root(camera))
        body = frame_name(config.body_frame or tree.static_top(camera))
    _attach_extrinsic(config, tree, body, camera)
    known = ", ".join(sorted(tree.frames)) or "none"
    for a, b, hint in ((world, body, "pass --set ingest.world_frame=NAME"), (body, camera, "pass --set ingest.extrinsic=x,y,z,qx,qy,qz,qw (T_body_camera)")):
        if a != b and (a not in tree.frames or b not in tree.frames or tree.root(a) != tree.root(b)):
            raise IngestError(f"no transform from frame {a!r} to frame {b!r} (tf frames: {known}); {hint}")
    # With a pose topic, /tf is only read again if a moving frame other than the body's lies on the
    # chain (e.g. a gimbal); skipping it halves the pose messages a bag like ours needs.
    moving = tree.dynamic_edges(world, camera)
    needs_dynamic_tf = pose_series is None or any(e is not pose_series for e in moving)
    return SourcePlan(**vars(roles), K=K, width=width, height=height, world_frame=world, body_frame=body,
                      camera_frame=camera, pose_parent=pose_parent, needs_dynamic_tf=needs_dynamic_tf)


def _read_until_planned(source: Source, roles: Roles, config: IngestConfig, camera: str) -> tuple[_PoseFeed, Any]:
    """Read pose, tf and camera-info messages until the plan can be made → (feed, first camera info or None)."""
    feed = _PoseFeed(roles.pose.topic, roles.tf_topics, config)  # learns the frames: every tf topic
    info_msg = None
    static_topics = [t for t in roles.tf_topics if "static" in t]
    static_seen = False

    def enough() -> bool:
        """Planning needs intrinsics, one pose, tf_static if recorded, and the camera in the tree."""
        if roles.camera_info.topic and info_msg is None:
            return False
        if roles.pose.topic and feed.pose_series is None:
            return False
        if not roles.pose.topic and not feed.tree.dynamic:
            return False
        if static_topics and not static_seen:
            return False
        if config.extrinsic is None and camera not in feed.tree.frames:
            return feed.pose_series is not None and feed.pose_series.child == camera
        return True

    wanted = feed.topics + ([roles.camera_info.topic] if roles.camera_info.topic else [])
    for raw in source.messages(wanted):
        if raw.topic == roles.camera_info.topic:
            info_msg = info_msg or source.deserialize(raw)
        else:
            feed.add(raw.topic, raw.msgtype, source.deserialize(raw))
            static_seen = static_seen or raw.topic in static_topics
        if enough():
            break
    if roles.pose.topic and feed.pose_series is None:
        raise IngestError(f"pose topic {roles.pose.topic} has no messages")
    return feed, info_msg


def _intrinsics(roles: Roles, config: IngestConfig, info_msg: Any) -> tuple[NDArray[np.float64], int, int]:
    """(K, width, height): ``--intrinsics`` (size 0: the images say) or the first camera info's."""
    if config.intrinsics is not None:
        return np.asarray(config.intrinsics, dtype=np.float64), 0, 0
    if info_msg is None:
        raise IngestError(f"camera info topic {roles.camera_info.topic} has no messages; pass --intrinsics fx,fy,cx,cy")
    return camera_intrinsics(info_msg, topic=roles.camera_info.topic or "")


def _body_of_pose_topic(roles: Roles, config: IngestConfig, tree: TfTree, pose_series: EdgeSeries, camera: str) -> str:
    """The body frame the pose topic locates: its child frame, ``body_frame``, or the top of the
    camera's static chain."""
    if pose_series.child:
        return frame_name(config.body_frame or pose_series.child)
    if config.body_frame:
        return frame_name(config.body_frame)
    if camera in tree.frames:
        return tree.static_top(camera)
    if config.extrinsic is not None:
        return "body"
    raise IngestError(
        f"pose topic {roles.pose.topic} ({(roles.pose.msgtype or '').split('/')[-1]}) does not name the frame it "
        f"locates and camera frame {camera!r} has no tf_static chain; pass --set ingest.extrinsic="
        "(T_body_camera as x,y,z,qx,qy,qz,qw, or 'identity' if the pose is the camera's)"
    )


def _attach_extrinsic(config: IngestConfig, tree: TfTree, body: str, camera: str) -> None:
    """Put ``extrinsic`` (T_body_camera) into the tree; with body == camera it must be the identity."""
    if config.extrinsic is None:
        return
    if body == camera:
        if not np.allclose(config.extrinsic, np.eye(4)):
            raise IngestError(f"body frame and camera frame are both {camera!r}; ingest.extrinsic must be 'identity'")
    else:
        tree.set_static(body, camera, np.asarray(config.extrinsic, dtype=np.float64))


_MAX_PENDING = 256  # depth frames held while waiting for later poses (the poses' lag behind depth)


@dataclass
class FrameStream:
    """Iterates frames of several recordings; after iteration, `dropped` and `used` say what happened.
    Each recording is read once: poses feed a tf tree, and each depth image waits until the poses
    around its stamp have arrived."""

    paths: list[Path]
    config: IngestConfig
    plans: list[SourcePlan] = field(default_factory=list)
    dropped: Counter = field(default_factory=Counter)
    used: int = 0
    depth_messages: int = 0
    warnings: list[str] = field(default_factory=list)
    _spans: dict[int, tuple[tuple[int, int], list[tuple[int, int]]]] = field(default_factory=dict)

    @property
    def K(self) -> NDArray[np.float64]:
        """(3, 3) intrinsics of the first recording (all recordings must share them)."""
        return self.plans[0].K

    @property
    def expected_frames(self) -> int:
        """Depth messages the stride keeps, over all recordings, capped by ``max_frames``."""
        n = sum(-(-p.summary.topics[p.depth.topic].count // self.config.stride) for p in self.plans)
        return min(n, self.config.max_frames) if self.config.max_frames else n

    def __iter__(self) -> Iterator[Frame]:
        for index, (path, plan) in enumerate(zip(self.paths, self.plans, strict=True)):
            for frame in self._iter_source(index, path, plan):
                if self.config.max_frames and self.used >= self.config.max_frames:
                    return
                self.used += 1
                yield frame
        if self.used == 0:
            raise IngestError(self._why_no_frames())

    def _iter_source(self, index: int, path: Path, plan: SourcePlan) -> Iterator[Frame]:
        """Frames of one recording in stamp order, each as soon as the poses around it have been read."""
        reader = _SourceReader(self, index, path, plan)
        with Source(path) as source:
            messages = source.messages([plan.depth.topic] + reader.feed.topics)
            # MCAP sources decompress in their own thread; the others read ahead in one here.
            cdr = source.kind != "ros1"
            for raw in messages if source.kind == "mcap" else prefetch(messages):
                if raw.topic != plan.depth.topic:
                    reader.add_pose_message(source, raw, cdr)
                elif not reader.add_depth_message(source, raw, cdr):
                    continue
                yield from reader.ready_frames(final=False)
            yield from reader.ready_frames(final=True)
        reader.finish()

    def _why_no_frames(self) -> str:
        reasons = ", ".join(f"{k}: {v}" for k, v in sorted(self.dropped.items())) or "none"
        msg = f"no usable frames out of {self.depth_messages} depth messages (dropped: {reasons})"
        if self.dropped.get(NO_POSE) and 0 in self._spans:
            (d0, d1), pose_spans = self._spans[0]
            if pose_spans:
                p0 = max(s[0] for s in pose_spans)
                p1 = min(s[1] for s in pose_spans)
                msg += (
                    f"; depth stamps span {d0 / 1e9:.3f}–{d1 / 1e9:.3f} s but poses span "
                    f"{p0 / 1e9:.3f}–{p1 / 1e9:.3f} s: no pose overlaps the depth stamps (different clocks?)"
                )
        elif self.dropped.get(POSE_GAP):
            msg += f"; raise ingest.max_pose_gap (now {self.config.max_pose_gap} s)"
        return msg


class _SourceReader:
    """Reading one planned recording: its pose feed, the depth frames waiting for their poses, and the
    stamps seen; counts go to the stream's ``dropped`` and ``depth_messages``."""

    def __init__(self, stream: FrameStream, index: int, path: Path, plan: SourcePlan) -> None:
        self.stream, self.index, self.path, self.plan = stream, index, path, plan
        self.max_gap_ns = int(round(stream.config.max_pose_gap * 1e9))
        self.feed = _PoseFeed.for_plan(plan, stream.config)
        self.tree = self.feed.tree
        self.pending: deque[tuple[int, Any, str]] = deque()
        self.first_stamp: int | None = None
        self.last_stamp: int | None = None
        self.n = -1  # index of the last depth message
        # Image size: the camera info's, or (with --intrinsics) the first image's.
        self.width, self.height = plan.width, plan.height
        self._edges_version = -1
        self._edges: list[EdgeSeries] = []  # moving edges world → camera at tree version _edges_version

    def add_pose_message(self, source: Source, raw: Any, cdr: bool) -> None:
        """Feed one pose or tf message to the tf tree (Odometry in CDR parsed without deserialising)."""
        odometry = cdr and raw.topic == self.plan.pose.topic and raw.msgtype == "nav_msgs/msg/Odometry"
        fast = parse_odometry(raw.data) if odometry else None
        if fast is not None:
            stamp, parent, child, t, q = fast
            self.feed.add_pose(raw.topic, stamp, frame_name(parent), frame_name(child) or None, t, q)
        else:
            self.feed.add(raw.topic, raw.msgtype, source.deserialize(raw))

    def add_depth_message(self, source: Source, raw: Any, cdr: bool) -> bool:
        """Queue one depth message; False when the stride skips it or its stamp goes backwards (dropped)."""
        config = self.stream.config
        self.n += 1
        self.stream.depth_messages += 1
        if self.n % config.stride:
            return False
        msg = parse_image(raw.data) if cdr and raw.msgtype == "sensor_msgs/msg/Image" else None
        msg = msg or source.deserialize(raw)
        stamp = stamp_ns(msg.header)
        self.first_stamp = stamp if self.first_stamp is None else self.first_stamp
        if self.last_stamp is not None and stamp <= self.last_stamp:
            if not config.drop_nonmonotonic:
                raise IngestError(
                    f"depth topic {self.plan.depth.topic} in {str(self.path)!r}: stamp goes backwards at "
                    f"message {self.n} ({stamp} ns after {self.last_stamp} ns); fix the recording's clock "
                    "or pass --set ingest.drop_nonmonotonic=true to drop such frames"
                )
            self.stream.dropped[NON_MONOTONIC] += 1
            return False
        self.last_stamp = stamp
        self.pending.append((stamp, msg, raw.msgtype))
        return True

    def ready_frames(self, *, final: bool) -> Iterator[Frame]:
        """The waiting frames whose poses have arrived, oldest first (all of them when ``final``)."""
        while self.pending and (final or self._ready(self.pending[0][0]) or len(self.pending) > _MAX_PENDING):
            if (frame := self._resolve(*self.pending.popleft())) is not None:
                yield frame

    def _ready(self, stamp: int) -> bool:
        """True when every moving edge world → camera has a sample at or after ``stamp``."""
        if self._edges_version != self.tree.version:
            self._edges_version = self.tree.version
            self._edges = self.tree.dynamic_edges(self.plan.world_frame, self.plan.camera_frame)
        return all(e.last_stamp is not None and e.last_stamp >= stamp for e in self._edges)

    def _resolve(self, stamp: int, msg: Any, msgtype: str) -> Frame | None:
        """Decode one depth message and pose it; None (counted in ``dropped``) without valid depth or pose."""
        plan = self.plan
        depth = decode_depth(msg, msgtype, topic=plan.depth.topic)
        if self.width and (depth.shape[1], depth.shape[0]) != (self.width, self.height):
            raise IngestError(
                f"depth topic {plan.depth.topic} has {depth.shape[1]}x{depth.shape[0]} images but its "
                f"camera info says {self.width}x{self.height}; pass --set ingest.camera_info_topic=TOPIC or --intrinsics"
            )
        if not self.width:
            self.height, self.width = depth.shape
        if not np.isfinite(depth).any():
            self.stream.dropped[NO_VALID_DEPTH] += 1
            return None
        try:
            T_world_body = self.tree.lookup(plan.world_frame, plan.body_frame, stamp, self.max_gap_ns)
            T_body_camera = self.tree.lookup(plan.body_frame, plan.camera_frame, stamp, self.max_gap_ns)
        except NoPose as missing:
            self.stream.dropped[missing.reason] += 1
            return None
        return Frame(depth, stamp, T_world_body @ T_body_camera, T_world_body, plan.K, self.index)

    def finish(self) -> None:
        """Count the dropped pose messages and keep the stamp spans for the no-frames message."""
        if self.feed.dropped_poses:
            self.stream.dropped["pose_message_non_monotonic"] += self.feed.dropped_poses
        edges = self.tree.dynamic_edges(self.plan.world_frame, self.plan.camera_frame)
        self.stream._spans[self.index] = ((self.first_stamp or 0, self.last_stamp or 0), [e.span for e in edges if len(e)])


def _refuse_duplicates(paths: list[Path]) -> None:
    """The same recording twice (by name, link or another spelling) would give every frame twice."""
    seen: dict[tuple[int, int], Path] = {}
    for path in paths:
        try:
            st = path.stat()
        except OSError:
            continue  # a missing input gets its own error when opened
        key = (st.st_dev, st.st_ino)
        if key in seen:
            raise IngestError(f"{str(path)!r} is the same recording as {str(seen[key])!r}; give each recording once")
        seen[key] = path


def _warn_overlap(stream: FrameStream, plan: SourcePlan) -> None:
    """Recordings whose time spans overlap are separate flights: their frames stay in input order,
    apart (``source_index``), and each flight's poses are used only for its own frames. Say so."""
    s = plan.summary
    for other in stream.plans:
        o = other.summary
        if other is not plan and s.start_ns < o.end_ns and o.start_ns < s.end_ns:
            stream.warnings.append(
                f"{str(s.path)!r} and {str(o.path)!r} overlap in time; they are kept as separate flights "
                "(frames in input order, each with its own recording's poses; source_index in frames.zarr)")
            return


def open_frames(paths: Sequence[str | Path], config: IngestConfig | None = None) -> FrameStream:
    """Plan the reading of one or more recordings (topics, intrinsics and frames checked up front,
    before any depth image is decoded); iterate the result for `Frame`s."""
    config = _checked(paths, config)
    stream = FrameStream([Path(p) for p in paths], config)
    _refuse_duplicates(stream.paths)
    for path in stream.paths:
        with Source(path) as source:
            plan = plan_source(source, config)
            stream.warnings.extend(source.summary.warnings)
        stream.plans.append(plan)
    first = stream.plans[0]
    for plan in stream.plans[1:]:
        if not np.allclose(plan.K, first.K) or (plan.width, plan.height) != (first.width, first.height):
            raise IngestError(
                f"{str(plan.summary.path)!r} has intrinsics {plan.K.ravel().tolist()} {plan.width}x{plan.height} "
                f"but {str(first.summary.path)!r} has {first.K.ravel().tolist()} {first.width}x{first.height}; "
                "ingest recordings of different cameras into separate workspaces"
            )
        _warn_overlap(stream, plan)
        if plan.world_frame != first.world_frame:
            raise IngestError(
                f"{str(plan.summary.path)!r} uses world frame {plan.world_frame!r} but "
                f"{str(first.summary.path)!r} uses {first.world_frame!r}; pass --set ingest.world_frame=NAME"
            )
    return stream


def _checked(paths: Sequence[str | Path], config: IngestConfig | None) -> IngestConfig:
    """``config`` (default: the defaults) once it and the list of ``paths`` are valid."""
    config = config or IngestConfig()
    config.validate()
    if not paths:
        raise IngestError("no input recordings given")
    return config


@dataclass
class RecordingInfo:
    """`mapkit info`: the summary of one recording plus its reading plan, or the reason there is none."""

    summary: BagSummary
    plan: SourcePlan | None
    problem: str | None


def inspect_recordings(paths: Sequence[str | Path], config: IngestConfig | None = None) -> list[RecordingInfo]:
    """Summaries and role choices for each recording. Unreadable inputs raise IngestError; a readable
    recording with no usable depth / camera info / pose gets a `problem`, so every input is listed."""
    config = _checked(paths, config)
    out = []
    for path in paths:
        with Source(path) as source:
            try:
                out.append(RecordingInfo(source.summary, plan_source(source, config), None))
            except IngestError as exc:
                out.append(RecordingInfo(source.summary, None, str(exc)))
    return out
