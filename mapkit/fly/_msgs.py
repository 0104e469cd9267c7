"""ROS 2 messages on DDS, from the definitions mapkit's readers use.

One typestore holds every message type `mapkit fly` speaks: rosbags' ROS 2 definitions (the ones
`mapkit ingest` reads bags with) plus PX4's, parsed from px4_msgs' own ``.msg`` files kept verbatim
beside this module. Cyclone DDS's Python binding needs a class per type; :func:`dds_type` derives it
from the typestore's field definitions, so nothing is written twice and nothing can drift. Its samples
carry the CDR as it crossed the wire: rosbags (de)serialises it (a 640×480 image in well under a
millisecond, where the binding's generic machinery builds a Python int per byte: 30 ms).
"""

from __future__ import annotations

from functools import cache
from pathlib import Path
from typing import Any

from mapkit.fly._errors import FlyError

_PX4_MSGS = Path(__file__).with_name("px4_msgs")

# rosbags field node kinds (rosbags.interfaces.Nodetype)
_BASE, _NAME, _ARRAY, _SEQUENCE = 1, 2, 3, 4


@cache
def typestore() -> Any:
    """rosbags' ROS 2 (Humble) typestore with px4_msgs' messages registered."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    for path in sorted(_PX4_MSGS.glob("*.msg")):
        store.register(get_types_from_msg(path.read_text(encoding="utf-8"), f"px4_msgs/msg/{path.stem}"))
    return store


def dds_typename(msgtype: str) -> str:
    """The DDS type name ROS 2 gives `msgtype`: ``sensor_msgs/msg/Image`` → ``sensor_msgs::msg::dds_::Image_``."""
    package, kind, name = msgtype.split("/")
    return f"{package}::{kind}::dds_::{name}_"


def _base_type(name: str, bound: int) -> Any:
    from cyclonedds.idl import types as idl_types

    types: Any = idl_types  # its generic aliases are indexable at run time, not to mypy

    if name == "string":
        return types.bounded_str[bound] if bound else str
    if name == "bool":
        return bool
    if name in ("byte", "char"):
        return types.uint8
    if hasattr(types, name) and name[0] in "iuf":
        return getattr(types, name)
    raise FlyError(f"message field type {name!r} has no DDS mapping in mapkit fly; use a message without it")


def _field_type(node: tuple[Any, Any]) -> Any:
    from cyclonedds.idl import types as idl_types

    types: Any = idl_types

    kind, arg = int(node[0]), node[1]
    if kind == _BASE:
        return _base_type(*arg)
    if kind == _NAME:
        return dds_type(arg)
    inner, size = arg
    element = _field_type(inner)
    if kind == _ARRAY:
        return types.array[element, size]
    return types.sequence[element, size] if size else types.sequence[element]


@cache
def dds_type(msgtype: str) -> Any:
    """The Cyclone DDS class of ROS 2 message type `msgtype`, derived from the typestore."""
    from cyclonedds.idl import make_idl_struct

    store = typestore()
    if msgtype not in store.fielddefs:
        raise FlyError(f"message type {msgtype!r} is unknown; known ones are ROS 2 Humble's and px4_msgs/msg/*")
    _, fields = store.fielddefs[msgtype]
    name = dds_typename(msgtype)
    kind = make_idl_struct(name.rsplit("::", 1)[1], name, {f: _field_type(node) for f, node in fields})
    # The class's fields give Cyclone the type's description (XTypes); its samples hold the CDR itself.
    setattr(kind, "serialize", _cdr_of)  # noqa: B010 - replacing the generated class's (de)serialisers
    setattr(kind, "deserialize", classmethod(_sample_of))  # noqa: B010
    return kind


def _cdr_of(sample: Any, buffer: Any = None, endianness: Any = None, use_version_2: Any = None) -> bytes:
    cdr: bytes = sample.cdr
    return cdr


def _sample_of(kind: type, data: bytes, has_header: bool = True, use_version_2: Any = None) -> Any:
    sample: Any = object.__new__(kind)
    sample.cdr = bytes(data)
    return sample


def encode(msg: Any, msgtype: str) -> bytes:
    """CDR (little-endian, with its encapsulation header) of a rosbags message object."""
    return bytes(typestore().serialize_cdr(msg, msgtype))


def decode(raw: bytes | memoryview, msgtype: str) -> Any:
    """A rosbags message object from CDR; :class:`FlyError` for bytes that are not one."""
    try:
        return typestore().deserialize_cdr(bytes(raw), msgtype)
    except Exception as exc:  # rosbags raises several kinds for truncated or foreign bytes
        raise FlyError(f"a {msgtype} message does not decode ({type(exc).__name__}: {exc})") from exc


def message(msgtype: str, **fields: Any) -> Any:
    """A rosbags message object of `msgtype` from its fields."""
    return typestore().types[msgtype](**fields)
