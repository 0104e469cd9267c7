"""Recordings → a stream of synchronised depth frames with camera and body poses."""

from __future__ import annotations

import logging
from collections import Counter, deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator, Sequence

import numpy as np
from numpy.typing import NDArray

from mapkit.geometry import transform_from_pose
from mapkit.ingest._decode import (
    ACCEPTED,
    CAMERA_INFO_TYPE,
    DEPTH_ENCODINGS,
    IMAGE_TYPES,
    POSE_TYPES,
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
from mapkit._threads import prefetch
from mapkit.ingest._sources import BagSummary, Source, normalize_topic
from mapkit.ingest._tf import NO_POSE, POSE_GAP, EdgeSeries, NoPose, TfTree

log = logging.getLogger(__name__)

NO_VALID_DEPTH = "no_valid_depth"
NON_MONOTONIC = "non_monotonic_stamp"


@dataclass
class IngestConfig:
    """How recordings are read. Every field has a CLI option of the same name."""

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
            raise IngestError(f"--max-pose-gap {self.max_pose_gap} must be positive (seconds)")
        if self.stride < 1:
            raise IngestError(f"--stride {self.stride} must be at least 1")
        if self.max_frames is not None and self.max_frames < 1:
            raise IngestError(f"--max-frames {self.max_frames} must be at least 1")

    def to_attrs(self) -> dict[str, Any]:
        out: dict[str, Any] = {}
        for key, value in self.__dict__.items():
            out[key] = value.tolist() if isinstance(value, np.ndarray) else value
        return out


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


@dataclass
class RoleChoice:
    topic: str | None
    msgtype: str | None
    why: str


@dataclass
class SourcePlan:
    """What will be read from one recording and why."""

    summary: BagSummary
    depth: RoleChoice
    depth_encoding: str
    camera_info: RoleChoice
    pose: RoleChoice
    tf_topics: list[str]
    K: NDArray[np.float64] | None = None
    width: int = 0
    height: int = 0
    world_frame: str = ""
    body_frame: str = ""
    camera_frame: str = ""
    pose_parent: str = ""
    needs_dynamic_tf: bool = True


def _find(summary: BagSummary, name: str, option: str) -> str:
    topic = normalize_topic(name)
    if topic not in summary.topics:
        raise IngestError(
            f"{option} {name}: no such topic in {str(summary.path)!r}; it has "
            + ", ".join(sorted(summary.topics))
        )
    return topic


class _EmptyTopic(IngestError):
    """A listed topic without messages (not damage)."""


def _first_message(source: Source, topic: str) -> Any:
    for raw in source.messages([topic]):
        return source.deserialize(raw)
    raise _EmptyTopic(f"topic {topic} in {str(source.path)!r} has no messages")


def choose_roles(source: Source, config: IngestConfig) -> SourcePlan:
    """Pick the depth, camera-info and pose topics of one recording (overrides first)."""
    s = source.summary
    by_type: dict[str, list[str]] = {}
    for t in s.topics.values():
        by_type.setdefault(t.msgtype, []).append(t.name)

    # Depth: an Image with a depth encoding or a compressedDepth CompressedImage.
    images = [t for mt in IMAGE_TYPES for t in by_type.get(mt, [])]
    if config.depth_topic:
        topic = _find(s, config.depth_topic, "--depth-topic")
        msgtype = s.topics[topic].msgtype
        if msgtype not in IMAGE_TYPES:
            raise IngestError(f"--depth-topic {topic} carries {msgtype}; expected sensor_msgs/Image or CompressedImage")
        enc = image_encoding(_first_message(source, topic), msgtype)
        if enc not in DEPTH_ENCODINGS + ("compressedDepth",):
            raise IngestError(f"topic {topic} has encoding {enc}; expected {ACCEPTED}; pass --depth-topic")
        depth = RoleChoice(topic, msgtype, "given by --depth-topic")
    else:
        seen: list[str] = []
        unreadable: list[str] = []
        candidates: list[tuple[tuple[int, int], str, str, str]] = []
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
            if enc in DEPTH_ENCODINGS + ("compressedDepth",):
                # Prefer names that say depth, raw over compressed, then the busiest topic.
                rank = ("depth" in topic.lower(), msgtype.endswith("/Image"))
                candidates.append(((int(rank[0]) * 2 + int(rank[1]), s.topics[topic].count), topic, msgtype, enc))
        if not candidates and unreadable:
            raise IngestError(f"{str(s.path)!r} lists image topics but cannot give their messages, so it is damaged "
                              f"({unreadable[0]})")
        if not candidates:
            listed = ", ".join(seen) if seen else "none"
            raise IngestError(
                f"no depth topic in {str(s.path)!r}: image topics seen: {listed}; expected encoding "
                f"{ACCEPTED}; pass --depth-topic"
            )
        candidates.sort(reverse=True)
        _, topic, msgtype, enc = candidates[0]
        others = [c[1] for c in candidates[1:]]
        why = f"{msgtype.split('/')[-1]} with encoding {enc}"
        if others:
            why += f"; preferred over {', '.join(others)} (name/type/count)"
        depth = RoleChoice(topic, msgtype, why)
    depth_encoding = image_encoding(_first_message(source, depth.topic), depth.msgtype)  # type: ignore[arg-type]

    # Camera info: the given one, else the CameraInfo sharing the depth topic's namespace.
    infos = by_type.get(CAMERA_INFO_TYPE, [])
    if config.camera_info_topic:
        topic = _find(s, config.camera_info_topic, "--camera-info-topic")
        camera_info = RoleChoice(topic, CAMERA_INFO_TYPE, "given by --camera-info-topic")
    elif config.intrinsics is not None:
        camera_info = RoleChoice(None, None, "--intrinsics given")
    elif infos:
        base = depth.topic.rsplit("/", 1)[0]  # type: ignore[union-attr]
        infos.sort(key=lambda t: (not t.startswith(base + "/"), "depth" not in t.lower(), t))
        why = "CameraInfo in the depth topic's namespace" if infos[0].startswith(base + "/") else "only CameraInfo topic" if len(infos) == 1 else "CameraInfo whose name says depth"
        camera_info = RoleChoice(infos[0], CAMERA_INFO_TYPE, why)
    else:
        raise IngestError(
            f"no camera info in {str(s.path)!r} (no sensor_msgs/CameraInfo topic); "
            "pass --intrinsics fx,fy,cx,cy"
        )

    # Pose: the given topic, else an Odometry, else a PoseStamped/-WithCovariance, else tf.
    tf_topics = sorted(by_type.get(TF_TYPE, []))
    if config.pose_topic and config.pose_topic.strip().lower() != "tf":
        topic = _find(s, config.pose_topic, "--pose-topic")
        msgtype = s.topics[topic].msgtype
        if msgtype not in POSE_TYPES:
            raise IngestError(
                f"--pose-topic {topic} carries {msgtype}; expected nav_msgs/Odometry, "
                "geometry_msgs/PoseStamped, PoseWithCovarianceStamped or TransformStamped (or 'tf')"
            )
        pose = RoleChoice(topic, msgtype, "given by --pose-topic")
    else:
        poses = [(mt, t) for mt in POSE_TYPES for t in by_type.get(mt, [])]
        if poses and not config.pose_topic:
            mt, topic = poses[0]
            same = [t for m, t in poses if m == mt]
            if len(same) > 1:
                topic = max(same, key=lambda t: s.topics[t].count)
            pose = RoleChoice(topic, mt, f"{mt.split('/')[-1]} topic" + (f"; preferred over {len(poses) - 1} other pose topic(s)" if len(poses) > 1 else ""))
        elif any(s.topics[t].count for t in tf_topics if "static" not in t):
            pose = RoleChoice(None, TF_TYPE, "no pose topic; world → camera from the tf tree")
        else:
            raise IngestError(
                f"no pose in {str(s.path)!r}: no Odometry/PoseStamped topic and no /tf; "
                "record one or pass --pose-topic"
            )
    return SourcePlan(s, depth, depth_encoding, camera_info, pose, tf_topics)


class _PoseFeed:
    """Turns pose, tf and tf_static messages into a TfTree as a recording streams by."""

    def __init__(self, plan: SourcePlan, config: IngestConfig, *, body: str | None = None) -> None:
        self.plan, self.config = plan, config
        self.tree = TfTree()
        self.pose_series: EdgeSeries | None = None
        self._last_pose_stamp: int | None = None
        self.dropped_poses = 0
        if body is not None and plan.pose.topic:
            # The pose topic defines world → body; tf's say about that edge is ignored.
            self.pose_series = EdgeSeries(plan.pose_parent, body, f"pose topic {plan.pose.topic}")
            self.tree.replace_dynamic(self.pose_series)
            self.tree.pinned.add(body)
        if body is not None and config.extrinsic is not None and body != plan.camera_frame:
            self.tree.set_static(body, plan.camera_frame, np.asarray(config.extrinsic, dtype=np.float64))
            self.tree.pinned.add(plan.camera_frame)

    @property
    def topics(self) -> list[str]:
        tf = [t for t in self.plan.tf_topics if self.plan.needs_dynamic_tf or "static" in t]
        return tf + ([self.plan.pose.topic] if self.plan.pose.topic else [])

    def add(self, topic: str, msgtype: str, msg: Any) -> None:
        if topic == self.plan.pose.topic:
            self.add_pose(topic, *pose_sample(msg, msgtype))
            return
        static = "static" in topic
        for stamp, parent, child, t, q in tf_samples(msg):
            if static:
                self.tree.set_static(parent, child, transform_from_pose(t, q))
            else:
                self.tree.add_dynamic(parent, child, stamp, t, q, f"topic {topic}")

    def add_pose(
        self, topic: str, stamp: int, parent: str, child: str | None, t: NDArray[np.float64], q: NDArray[np.float64]
    ) -> None:
        """One sample of the pose topic (parent → child frame)."""
        last = self._last_pose_stamp
        if last is not None and stamp < last:
            if not self.config.drop_nonmonotonic:
                raise IngestError(
                    f"pose topic {topic}: stamp goes backwards ({stamp} ns after {last} ns); fix the "
                    "recording's clock or pass --drop-nonmonotonic to drop such messages"
                )
            self.dropped_poses += 1
            return
        self._last_pose_stamp = stamp
        if self.pose_series is None:  # planning: the body frame is not known yet
            self.pose_series = EdgeSeries(parent, child or "", f"pose topic {topic}")
        self.pose_series.add(stamp, t, q)


def load_poses(source: Source, plan: SourcePlan, config: IngestConfig) -> None:
    """Resolve intrinsics and the world / body / camera frames from the first seconds of a recording."""
    feed = _PoseFeed(plan, config)
    info_msg = None
    first = _first_message(source, plan.depth.topic)  # type: ignore[arg-type]
    camera = frame_name(config.camera_frame or first.header.frame_id)
    if not camera:
        raise IngestError(f"depth topic {plan.depth.topic} has an empty header.frame_id; pass --camera-frame")
    static_topics = [t for t in plan.tf_topics if "static" in t]
    static_seen = False

    def enough() -> bool:
        """Planning needs intrinsics, one pose, tf_static if recorded, and the camera in the tree."""
        if plan.camera_info.topic and info_msg is None:
            return False
        if plan.pose.topic and feed.pose_series is None:
            return False
        if not plan.pose.topic and not feed.tree.dynamic:
            return False
        if static_topics and not static_seen:
            return False
        if config.extrinsic is None and camera not in feed.tree.frames:
            return feed.pose_series is not None and feed.pose_series.child == camera
        return True

    wanted = feed.topics + ([plan.camera_info.topic] if plan.camera_info.topic else [])
    for raw in source.messages(wanted):
        if raw.topic == plan.camera_info.topic:
            info_msg = info_msg or source.deserialize(raw)
        else:
            feed.add(raw.topic, raw.msgtype, source.deserialize(raw))
            static_seen = static_seen or raw.topic in static_topics
        if enough():
            break
    if plan.pose.topic and feed.pose_series is None:
        raise IngestError(f"pose topic {plan.pose.topic} has no messages")
    tree, pose_series = feed.tree, feed.pose_series

    if config.intrinsics is not None:
        plan.K = np.asarray(config.intrinsics, dtype=np.float64)
    else:
        if info_msg is None:
            raise IngestError(
                f"camera info topic {plan.camera_info.topic} has no messages; pass --intrinsics fx,fy,cx,cy"
            )
        plan.K, plan.width, plan.height = camera_intrinsics(info_msg, topic=plan.camera_info.topic or "")

    if pose_series is not None:
        if pose_series.child:
            body = frame_name(config.body_frame or pose_series.child)
        elif config.body_frame:
            body = frame_name(config.body_frame)
        elif camera in tree.frames:
            body = tree.static_top(camera)
        elif config.extrinsic is not None:
            body = "body"
        else:
            raise IngestError(
                f"pose topic {plan.pose.topic} ({plan.pose.msgtype.split('/')[-1]}) does not name the frame it "  # type: ignore[union-attr]
                f"locates and camera frame {camera!r} has no tf_static chain; pass --extrinsic "
                "(T_body_camera as x,y,z,qx,qy,qz,qw, or 'identity' if the pose is the camera's)"
            )
        plan.pose_parent = pose_series.parent
        pose_series.child = body
        tree.replace_dynamic(pose_series)
        world = frame_name(config.world_frame or pose_series.parent)
    else:
        if camera not in tree.frames:
            raise IngestError(
                f"camera frame {camera!r} is not in the tf tree (frames: {', '.join(sorted(tree.frames)) or 'none'}); "
                "pass --camera-frame or --pose-topic"
            )
        world = frame_name(config.world_frame or tree.root(camera))
        body = frame_name(config.body_frame or tree.static_top(camera))
    if config.extrinsic is not None:
        if body == camera:
            if not np.allclose(config.extrinsic, np.eye(4)):
                raise IngestError(f"body frame and camera frame are both {camera!r}; --extrinsic must be 'identity'")
        else:
            tree.set_static(body, camera, np.asarray(config.extrinsic, dtype=np.float64))
    known = ", ".join(sorted(tree.frames)) or "none"
    for a, b, hint in ((world, body, "pass --world-frame"), (body, camera, "pass --extrinsic x,y,z,qx,qy,qz,qw (T_body_camera)")):
        if a != b and (a not in tree.frames or b not in tree.frames or not tree.connected(a, b)):
            raise IngestError(f"no transform from frame {a!r} to frame {b!r} (tf frames: {known}); {hint}")
    plan.world_frame, plan.body_frame, plan.camera_frame = world, body, camera
    # With a pose topic, /tf is only read again if a moving frame other than the body's lies on the
    # chain (e.g. a gimbal); skipping it halves the pose messages a bag like ours needs.
    moving = tree.dynamic_edges(world, camera)
    plan.needs_dynamic_tf = pose_series is None or any(e is not pose_series for e in moving)


_MAX_PENDING = 256  # depth frames held while waiting for later poses (the poses' lag behind depth)


@dataclass
class FrameStream:
    """Iterates frames of several recordings; after iteration, `dropped` and `used` say what happened.

    Each recording is read once, in log-time order: poses and tf feed a growing tf tree, and each
    depth image waits (serialised) until the poses around its stamp have arrived. Only poses and a
    short queue of images are held in memory.
    """

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
        return self.plans[0].K  # type: ignore[return-value]

    @property
    def expected_frames(self) -> int:
        n = sum(-(-p.summary.topics[p.depth.topic].count // self.config.stride) for p in self.plans)  # type: ignore[index]
        return min(n, self.config.max_frames) if self.config.max_frames else n

    def __iter__(self) -> Iterator[Frame]:
        for index, (path, plan) in enumerate(zip(self.paths, self.plans)):
            for frame in self._iter_source(index, path, plan):
                if self.config.max_frames and self.used >= self.config.max_frames:
                    return
                self.used += 1
                yield frame
        if self.used == 0:
            raise IngestError(self._why_no_frames())

    def _iter_source(self, index: int, path: Path, plan: SourcePlan) -> Iterator[Frame]:
        max_gap_ns = int(round(self.config.max_pose_gap * 1e9))
        feed = _PoseFeed(plan, self.config, body=plan.body_frame)
        tree = feed.tree
        pending: deque[tuple[int, Any, str]] = deque()
        first_stamp: int | None = None
        last_stamp: int | None = None
        n = -1

        def resolve(stamp: int, msg: Any, msgtype: str) -> Frame | None:
            depth = decode_depth(msg, msgtype, topic=plan.depth.topic or "")
            if plan.width and (depth.shape[1], depth.shape[0]) != (plan.width, plan.height):
                raise IngestError(
                    f"depth topic {plan.depth.topic} has {depth.shape[1]}x{depth.shape[0]} images but its "
                    f"camera info says {plan.width}x{plan.height}; pass --camera-info-topic or --intrinsics"
                )
            if not plan.width:
                plan.height, plan.width = depth.shape
            if not np.isfinite(depth).any():
                self.dropped[NO_VALID_DEPTH] += 1
                return None
            try:
                T_world_body = tree.lookup(plan.world_frame, plan.body_frame, stamp, max_gap_ns)
                T_body_camera = tree.lookup(plan.body_frame, plan.camera_frame, stamp, max_gap_ns)
            except NoPose as missing:
                self.dropped[missing.reason] += 1
                return None
            return Frame(depth, stamp, T_world_body @ T_body_camera, T_world_body, plan.K, index)  # type: ignore[arg-type]

        edges_cache: list[Any] = [-1, []]  # [tree version, moving edges world → camera]

        def ready(stamp: int) -> bool:
            if edges_cache[0] != tree.version:
                edges_cache[:] = [tree.version, tree.dynamic_edges(plan.world_frame, plan.camera_frame)]
            return all(e.last_stamp is not None and e.last_stamp >= stamp for e in edges_cache[1])

        with Source(path) as source:
            messages = source.messages([plan.depth.topic] + feed.topics)  # type: ignore[list-item]
            # MCAP sources decompress in their own thread; the others read ahead in one here.
            cdr = source.kind != "ros1"
            for raw in messages if source.kind == "mcap" else prefetch(messages):
                if raw.topic != plan.depth.topic:
                    fast = None
                    if cdr and raw.topic == plan.pose.topic and raw.msgtype == "nav_msgs/msg/Odometry":
                        fast = parse_odometry(raw.data)
                    if fast is not None:
                        stamp, parent, child, t, q = fast
                        feed.add_pose(raw.topic, stamp, frame_name(parent), frame_name(child) or None, t, q)
                    else:
                        feed.add(raw.topic, raw.msgtype, source.deserialize(raw))
                else:
                    n += 1
                    self.depth_messages += 1
                    if n % self.config.stride:
                        continue
                    msg = parse_image(raw.data) if cdr and raw.msgtype == "sensor_msgs/msg/Image" else None
                    msg = msg or source.deserialize(raw)
                    stamp = stamp_ns(msg.header)
                    first_stamp = stamp if first_stamp is None else first_stamp
                    if last_stamp is not None and stamp <= last_stamp:
                        if not self.config.drop_nonmonotonic:
                            raise IngestError(
                                f"depth topic {plan.depth.topic} in {str(path)!r}: stamp goes backwards at "
                                f"message {n} ({stamp} ns after {last_stamp} ns); fix the recording's clock "
                                "or pass --drop-nonmonotonic to drop such frames"
                            )
                        self.dropped[NON_MONOTONIC] += 1
                        continue
                    last_stamp = stamp
                    pending.append((stamp, msg, raw.msgtype))
                while pending and (ready(pending[0][0]) or len(pending) > _MAX_PENDING):
                    if (frame := resolve(*pending.popleft())) is not None:
                        yield frame
            while pending:
                if (frame := resolve(*pending.popleft())) is not None:
                    yield frame
        self.dropped["pose_message_non_monotonic"] += feed.dropped_poses
        if not self.dropped["pose_message_non_monotonic"]:
            del self.dropped["pose_message_non_monotonic"]
        edges = tree.dynamic_edges(plan.world_frame, plan.camera_frame)
        self._spans[index] = ((first_stamp or 0, last_stamp or 0), [e.span for e in edges if len(e)])

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
            msg += f"; raise --max-pose-gap (now {self.config.max_pose_gap} s)"
        return msg


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
    """Plan the reading of one or more recordings; iterate the result for `Frame`s.

    Checks every recording's topics, intrinsics and frames up front (reading only the small pose
    and tf topics), so mistakes surface before any depth image is decoded.
    """
    config = config or IngestConfig()
    config.validate()
    if not paths:
        raise IngestError("no input recordings given")
    stream = FrameStream([Path(p) for p in paths], config)
    _refuse_duplicates(stream.paths)
    for path in stream.paths:
        with Source(path) as source:
            plan = choose_roles(source, config)
            load_poses(source, plan, config)
            stream.warnings.extend(source.summary.warnings)
        stream.plans.append(plan)
    first = stream.plans[0]
    for plan in stream.plans[1:]:
        if not np.allclose(plan.K, first.K) or (plan.width, plan.height) != (first.width, first.height):  # type: ignore[arg-type]
            raise IngestError(
                f"{str(plan.summary.path)!r} has intrinsics {plan.K.ravel().tolist()} {plan.width}x{plan.height} "  # type: ignore[union-attr]
                f"but {str(first.summary.path)!r} has {first.K.ravel().tolist()} {first.width}x{first.height}; "  # type: ignore[union-attr]
                "ingest recordings of different cameras into separate workspaces"
            )
        _warn_overlap(stream, plan)
        if plan.world_frame != first.world_frame:
            raise IngestError(
                f"{str(plan.summary.path)!r} uses world frame {plan.world_frame!r} but "
                f"{str(first.summary.path)!r} uses {first.world_frame!r}; pass --world-frame"
            )
    return stream
