"""Settings from the typed configs: ``--config FILE.toml`` and ``--set KEY=VALUE`` on every command
backed by config dataclasses, the TOML that ``mapkit config COMMAND`` prints, and options whose default
is read from the dataclass (one place for each default).

A key is a field's name, a nested dataclass a table (``loop.pilot.replan_interval``); a value is TOML,
and on ``--set`` a bare word is text and a comma list fills a list. TOML has no null: ``"none"`` stands
for None. Precedence, lowest first: the dataclass defaults (train: its preset), ``--config``, the
command's own options, ``--set``. The help of a field is the docstring under it, read from the source
with ast (once per class): the same text the library documents.
"""

from __future__ import annotations

import ast
import dataclasses
import difflib
import functools
import inspect
import itertools
import json
import math
import re
import textwrap
import tomllib
import types
import typing
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, Union

import click

from mapkit.errors import MapkitError

NONE = "none"
"""The value that stands for None (TOML has no null)."""


@dataclass(frozen=True)
class Codec:
    """A field whose value is not plain TOML (a camera list written as text, an intrinsics matrix):
    ``read`` turns the TOML value into the field's value (raising ValueError or a MapkitError naming the
    fix), ``show`` the field's value into TOML."""

    read: Callable[[Any], Any]
    show: Callable[[Any], Any]


@dataclass(eq=False)
class ConfigSpec:
    """The settings of one command: its config dataclasses, each at a key prefix ("" = top level)."""

    command: str
    """The command's path below ``mapkit`` (``eval``, ``lab tune-timing``)."""
    tables: tuple[tuple[str, Callable[[], Any]], ...]
    """(prefix, factory of the default instance); the library is imported only when one is called."""
    hidden: frozenset[str] = frozenset()
    """Keys the command does not offer (research-only fields; what its arguments give)."""
    codecs: dict[str, Codec] = field(default_factory=dict)
    """Keys whose value is not plain TOML."""
    note: str = ""
    """A line for the head of ``mapkit config COMMAND`` (where the defaults come from)."""
    example: str = ""
    """A ``KEY=VALUE`` for the help of --set."""

    @functools.cached_property
    def defaults(self) -> dict[str, Any]:
        """The default instance of each table, by prefix."""
        return {prefix: make() for prefix, make in self.tables}

    @functools.cached_property
    def entries(self) -> dict[str, Entry]:
        """Every key the command takes, tables included, in declaration order."""
        out: dict[str, Entry] = {}
        for prefix, instance in self.defaults.items():
            if prefix:
                out[prefix] = Entry(prefix, type(instance), _class_doc(type(instance)), type(instance), False)
            _walk(type(instance), prefix, self.hidden, out)
        return out

    def default(self, key: str) -> Any:
        """The default value of ``key``."""
        parent, name = self._parent(key)
        return getattr(parent, name) if name else parent

    def doc(self, key: str) -> str:
        """The docstring of ``key``'s field (hidden keys too: an option may fill one)."""
        parent, name = self._parent(key)
        cls: type = type(parent)
        return field_docs(cls).get(name, "") if name else _class_doc(cls)

    def _parent(self, key: str) -> tuple[Any, str]:
        """The default instance holding ``key``'s field, and the field's name ("" for a table's root)."""
        prefix = next((p for p in self.defaults if p and (key == p or key.startswith(p + "."))), "")
        value = self.defaults[prefix]
        *parents, name = _split(key[len(prefix):]) or [""]
        for part in parents:
            owner: type = type(value)
            value = getattr(value, part)
            if value is None:  # a layer off by default: its fields' defaults are its class's
                table, _ = _table_of(_hints(owner).get(part))
                value = table() if table is not None else value
        return value, name


@dataclass(frozen=True)
class Entry:
    """One key: its type, its docstring, and the dataclass when it is a table."""

    key: str
    hint: Any
    doc: str
    table: type | None
    optional: bool
    """The field may be None (``"none"``)."""


SPECS: dict[str, ConfigSpec] = {}
"""Every command's settings, by command path (filled as the command modules register)."""


class _Bad(Exception):
    """A value of the wrong type; ``expected`` says what the field takes."""

    def __init__(self, expected: str) -> None:
        super().__init__(expected)
        self.expected = expected


def _split(key: str) -> list[str]:
    return [part for part in key.split(".") if part]


def _join(prefix: str, name: str) -> str:
    return f"{prefix}.{name}" if prefix else name


@functools.cache
def _hints(cls: type) -> dict[str, Any]:
    try:
        return typing.get_type_hints(cls)
    except (NameError, TypeError):  # a name imported for type checking only: the value is passed as given
        return {f.name: Any for f in dataclasses.fields(cls)}


@functools.cache
def field_docs(cls: type) -> dict[str, str]:
    """The docstring under each field of dataclass ``cls`` (and of its dataclass bases)."""
    docs: dict[str, str] = {}
    for klass in reversed(cls.__mro__):
        if not dataclasses.is_dataclass(klass):
            continue
        try:
            tree = ast.parse(textwrap.dedent(inspect.getsource(klass)))
        except (OSError, TypeError):
            continue
        body = tree.body[0].body if tree.body and isinstance(tree.body[0], ast.ClassDef) else []
        for node, after in itertools.pairwise(body):
            if (isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name) and isinstance(after, ast.Expr)
                    and isinstance(after.value, ast.Constant) and isinstance(after.value.value, str)):
                docs[node.target.id] = inspect.cleandoc(after.value.value)
    return docs


def _class_doc(cls: type) -> str:
    return inspect.cleandoc(cls.__doc__ or "").split("\n\n")[0]


_ROLE = re.compile(r":\w+:`(~?)([^`]+)`")


def plain(doc: str) -> str:
    """A docstring as plain text: Sphinx roles and double backquotes as `name`, one paragraph per line."""
    text = _ROLE.sub(lambda m: f"`{m.group(2).rsplit('.', 1)[-1] if m.group(1) else m.group(2)}`", doc)
    return "\n".join(" ".join(p.split()) for p in text.replace("``", "`").split("\n\n"))


def _table_of(hint: Any) -> tuple[type | None, bool]:
    """The dataclass a field holds (or None) and whether the field may be None."""
    args = typing.get_args(hint) if typing.get_origin(hint) in (Union, types.UnionType) else (hint,)
    optional = type(None) in args
    rest = [a for a in args if a is not type(None)]
    table = rest[0] if len(rest) == 1 and isinstance(rest[0], type) and dataclasses.is_dataclass(rest[0]) else None
    return table, optional


def _walk(cls: type, prefix: str, hidden: frozenset[str], out: dict[str, Entry]) -> None:
    hints, docs = _hints(cls), field_docs(cls)
    for f in dataclasses.fields(cls):
        key = _join(prefix, f.name)
        no_default = f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING
        if f.name.startswith("_") or not f.init or no_default or key in hidden:  # private, or an argument's
            continue
        hint = hints.get(f.name, Any)
        table, optional = _table_of(hint)
        out[key] = Entry(key, hint, docs.get(f.name, ""), table, optional)
        if table is not None:
            _walk(table, key, hidden, out)


# --- values -----------------------------------------------------------------------------------------


def toml_value(text: str) -> Any:
    """``text`` read as one TOML value; what is not TOML (a bare word, a comma list) stays text."""
    try:
        return tomllib.loads(f"v = {text}")["v"]
    except tomllib.TOMLDecodeError:
        return text


def _items(value: Any) -> list[Any]:
    if isinstance(value, (list, tuple)):
        return list(value)
    if isinstance(value, str):  # a comma list: "office,forest", "0.2,0.4,0.4"
        return [toml_value(part.strip()) for part in value.split(",") if part.strip()]
    raise _Bad("a list")


def _describe(hint: Any) -> str:
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin in (Union, types.UnionType):
        return " or ".join(f'"{NONE}"' if a is type(None) else _describe(a) for a in args)
    if origin is Literal:
        return "one of " + ", ".join(json.dumps(a) for a in args)
    if origin is tuple:
        if len(args) == 2 and args[1] is Ellipsis:
            return f"a list of ({_describe(args[0])})"
        return f"a list of {len(args)} ({', '.join(_describe(a) for a in args)})"
    names = {bool: "true or false", int: "an integer", float: "a finite number", str: "text", dict: "a table"}
    return names.get(hint, getattr(hint, "__name__", str(hint)))


def convert(value: Any, hint: Any) -> Any:
    """``value`` (from TOML) as a value of type ``hint``; :class:`_Bad` when it is not one."""
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if hint is Any:
        return value
    if origin in (Union, types.UnionType):
        if type(None) in args and value in (None, NONE):
            return None
        for arg in (a for a in args if a is not type(None)):
            try:
                return convert(value, arg)
            except _Bad:
                pass
        raise _Bad(_describe(hint))
    if origin is Literal:
        if value in args:
            return value
        raise _Bad(_describe(hint))
    if origin is tuple:
        items = _items(value)
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(convert(v, args[0]) for v in items)
        if len(items) != len(args):
            raise _Bad(_describe(hint))
        return tuple(convert(v, a) for v, a in zip(items, args, strict=True))
    return _scalar(value, hint)


def _scalar(value: Any, hint: Any) -> Any:
    ok = {bool: isinstance(value, bool), int: isinstance(value, int) and not isinstance(value, bool),
          float: isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value),
          str: isinstance(value, str), dict: isinstance(value, dict),
          Path: isinstance(value, (str, Path))}
    if hint in ok:
        if not ok[hint]:
            raise _Bad(_describe(hint))
        return float(value) if hint is float else Path(value) if hint is Path else value
    if typing.get_origin(hint) is dict:
        if not isinstance(value, dict):
            raise _Bad("a table")
        return value
    if isinstance(hint, type) and dataclasses.is_dataclass(hint):
        raise _Bad("a table")
    return value  # a type this does not know: the dataclass's validate() decides


def to_toml(value: Any) -> str:
    """``value`` written as a TOML value (None as ``"none"``)."""
    if value is None:
        return json.dumps(NONE)
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return repr(value) if math.isfinite(value) else ("nan" if math.isnan(value) else "inf" if value > 0 else "-inf")
    if isinstance(value, int):
        return str(value)
    if isinstance(value, (str, Path)):
        return json.dumps(str(value), ensure_ascii=False)
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        value = {f.name: getattr(value, f.name) for f in dataclasses.fields(value)}
    if isinstance(value, dict):
        return "{ " + ", ".join(f"{json.dumps(str(k))} = {to_toml(v)}" for k, v in value.items()) + " }" if value else "{}"
    if hasattr(value, "tolist"):  # numpy
        return to_toml(value.tolist())
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(to_toml(v) for v in value) + "]"
    return json.dumps(str(value))


# --- reading --config and --set ------------------------------------------------------------------------


class SettingError(click.UsageError):
    """A bad key or value in --config or --set: a usage error (exit 2) naming it and the fix."""

    def __init__(self, message: str) -> None:
        super().__init__(message, click.get_current_context(silent=True))


def _unknown(spec: ConfigSpec, key: str, source: str) -> SettingError:
    known = list(spec.entries)
    close = difflib.get_close_matches(key, known, n=3, cutoff=0.6)
    leaf = _split(key)[-1] if _split(key) else key
    close += [k for k in known if k not in close and difflib.get_close_matches(leaf, [_split(k)[-1]], cutoff=0.75)]
    hint = f"; closest: {', '.join(close[:3])}" if close else ""
    return SettingError(f"{source}: mapkit {spec.command} has no setting {key!r}{hint}; "
                        f"`mapkit config {spec.command}` lists every one with its default")


def _assign(flat: dict[str, Any], key: str, value: Any) -> None:
    """Set ``key``: what was set below it (a table replaced) or above it (a table set to none) goes."""
    for other in [k for k in flat if k.startswith(key + ".") or key.startswith(k + ".")]:
        del flat[other]
    flat[key] = value


def _put(spec: ConfigSpec, flat: dict[str, Any], key: str, value: Any, source: str, raw: str | None = None) -> None:
    """Check ``value`` for ``key`` and set it in ``flat``; a table's value sets the fields it names."""
    entry = spec.entries.get(key)
    if entry is None:
        raise _unknown(spec, key, source)
    if entry.table is not None:
        if isinstance(value, dict):
            for name, sub in value.items():
                _put(spec, flat, _join(key, str(name)), sub, source)
            return
        if not (entry.optional and value in (None, NONE)):
            raise SettingError(f"{source}: {key} is a table of settings ({', '.join(_children(spec, key))}); set them "
                               f"one by one (--set {key}.NAME=VALUE)" + (f' or turn it off with "{NONE}"' if entry.optional else ""))
        _assign(flat, key, None)
        return
    _assign(flat, key, _converted(spec, entry, value, source, raw))


def _converted(spec: ConfigSpec, entry: Entry, value: Any, source: str, raw: str | None) -> Any:
    codec = spec.codecs.get(entry.key)
    try:
        if codec is not None:
            return None if entry.optional and value in (None, NONE) else codec.read(value)
        try:
            return convert(value, entry.hint)
        except _Bad:
            if raw is None or isinstance(value, str):
                raise
            return convert(raw, entry.hint)  # --set name=2024: text where text is wanted
    except _Bad as exc:
        example = to_toml(_shown(spec, entry.key))
        raise SettingError(f"{source}: {entry.key} takes {exc.expected}, got {to_toml(value)} "
                           f"(e.g. {entry.key} = {example})") from None
    except (ValueError, TypeError, MapkitError) as exc:  # a codec's reader refused it
        raise SettingError(f"{source}: {entry.key}: {' '.join(str(exc).split())}") from None


def _children(spec: ConfigSpec, key: str) -> list[str]:
    return [k[len(key) + 1:] for k in spec.entries if k.startswith(key + ".") and "." not in k[len(key) + 1:]]


def _shown(spec: ConfigSpec, key: str) -> Any:
    value = spec.default(key)
    codec = spec.codecs.get(key)
    return codec.show(value) if codec is not None and value is not None else value


@dataclass
class Settings:
    """A command's --config and --set, checked against its dataclasses (flat dotted keys)."""

    spec: ConfigSpec
    file: dict[str, Any] = field(default_factory=dict)
    sets: dict[str, Any] = field(default_factory=dict)

    def given(self, key: str) -> bool:
        """Whether --config or --set named ``key``."""
        return key in self.file or key in self.sets

    def resolve(self, options: dict[str, Any] | None = None) -> dict[str, Any]:
        """Every key given, by precedence: --config, then the command's options (``options``, dotted keys;
        None: not given), then --set."""
        flat: dict[str, Any] = {}
        given = {k: v for k, v in (options or {}).items() if v is not None}
        for layer in (self.file, given, self.sets):
            for key, value in layer.items():
                _assign(flat, key, value)
        return flat

    def build(self, base: Any, options: dict[str, Any] | None = None, table: str = "") -> Any:
        """``base`` (a config dataclass, the table at ``table``) with the settings applied."""
        return _apply(base, self.resolve(options), table)

    def nested(self, options: dict[str, Any] | None = None, table: str = "") -> dict[str, Any]:
        """The settings of ``table`` as nested dicts (``{"planner": {"accel": 1.5}}``)."""
        out: dict[str, Any] = {}
        for key, value in self.resolve(options).items():
            if table and not key.startswith(table + "."):
                continue
            *parents, name = _split(key[len(table):])
            node = out
            for parent in parents:
                node = node.setdefault(parent, {})
            node[name] = value
        return out


def _apply(obj: Any, flat: dict[str, Any], prefix: str) -> Any:
    """``obj`` with the keys of ``flat`` under ``prefix`` applied; nested dataclasses are rebuilt with
    ``replace`` (most configs are frozen), so a key changes its field and nothing else."""
    changes: dict[str, Any] = {}
    for f in dataclasses.fields(obj):
        key = _join(prefix, f.name)
        if key in flat:
            changes[f.name] = flat[key]
        elif any(k.startswith(key + ".") for k in flat):
            current = getattr(obj, f.name)
            if current is None:  # a layer that was off, set field by field: from its defaults
                owner: type = type(obj)
                table, _ = _table_of(_hints(owner).get(f.name))
                current = table() if table is not None else current
            changes[f.name] = _apply(current, flat, key)
    return dataclasses.replace(obj, **changes) if changes else obj


def read_settings(spec: ConfigSpec, path: Path | None, items: tuple[str, ...]) -> Settings:
    """--config ``path`` and the --set ``items``, checked: an unknown key or a bad value is a usage error."""
    settings = Settings(spec)
    if path is not None:
        try:
            data = tomllib.loads(Path(path).read_text(encoding="utf-8"))
        except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
            raise SettingError(f"--config {path}: not TOML ({exc}); `mapkit config {spec.command}` prints a valid "
                               "file") from None
        for key, value in data.items():
            _put(spec, settings.file, key, value, f"--config {path}")
    for item in items:
        key, sep, raw = item.partition("=")
        if not sep or not key.strip():
            raise SettingError(f"--set {item!r}: expected KEY=VALUE (e.g. --set {spec.example or 'KEY=VALUE'}); "
                               f"`mapkit config {spec.command}` lists the keys")
        raw = raw.strip()
        _put(spec, settings.sets, key.strip(), toml_value(raw), f"--set {item}", raw)
    return settings


def config_options(spec: ConfigSpec) -> Callable[[Callable[..., Any]], Callable[..., Any]]:
    """``--config FILE.toml`` and ``--set KEY=VALUE`` for a command (put it right above
    ``@library_call``: the two come last in --help); the command gets ``settings`` (:class:`Settings`)."""
    SPECS[spec.command] = spec

    def decorate(func: Callable[..., Any]) -> Callable[..., Any]:
        @functools.wraps(func)
        def run(*args: Any, config_file: Path | None, set_items: tuple[str, ...], **kwargs: Any) -> Any:
            return func(*args, settings=read_settings(spec, config_file, set_items), **kwargs)

        click.option("--set", "set_items", multiple=True, metavar="KEY=VALUE",
                     help=f"One setting, e.g. --set {spec.example or 'KEY=VALUE'} (repeatable; VALUE is TOML, a bare word is "
                          f"text, \"{NONE}\" is unset); it overrides --config and the options above. Every key: "
                          f"`mapkit config {spec.command}`.")(run)
        click.option("--config", "config_file", type=click.Path(exists=True, dir_okay=False, path_type=Path),
                     metavar="FILE.toml",
                     help=f"Settings from a TOML file (`mapkit config {spec.command}` prints every one with its "
                          "default); the options above override it.")(run)
        return run

    return decorate



# --- what `mapkit config COMMAND` prints -------------------------------------------------------------


def render(spec: ConfigSpec) -> str:
    """Every setting of ``spec``'s command as TOML: each key at its default, its docstring above it."""
    lines = [f"# mapkit {spec.command}: every setting at its default; use with `mapkit {spec.command} --config FILE.toml`",
             "# (or one at a time: --set KEY=VALUE). Lowest to highest: these defaults, --config, the command's",
             f'# options, --set. "{NONE}" stands for an unset value (TOML has no null).']
    if spec.note:
        lines += _comment(spec.note)
    for prefix, instance in spec.defaults.items():
        _render_table(spec, instance, prefix, lines)
    return "\n".join(lines) + "\n"


def _comment(text: str) -> list[str]:
    return [f"# {line}" if line else "#" for paragraph in plain(text).split("\n")
            for line in textwrap.wrap(paragraph, 96) or [""]]


def _render_table(spec: ConfigSpec, obj: Any, key: str, lines: list[str]) -> None:
    if key:
        lines += ["", *_comment(spec.entries[key].doc), f"[{key}]"]
    tables = []
    for f in dataclasses.fields(obj):
        entry = spec.entries.get(_join(key, f.name))
        if entry is None:
            continue
        value = getattr(obj, f.name)
        if entry.table is not None and value is not None:
            tables.append((entry.key, value))
            continue
        lines += ["", *_comment(entry.doc), f"{f.name} = {to_toml(_shown(spec, entry.key))}"]
    for sub, value in tables:
        _render_table(spec, value, sub, lines)


# --- options that fill one field -----------------------------------------------------------------------


class FieldOption(click.Option):
    """An option that fills one config field: it has no default of its own (None: not given, the field's
    default applies), and its --help shows the dataclass's default and, without a help text of its own,
    the field's docstring; both are read only when help is shown, so the CLI starts without the library."""

    def __init__(self, *args: Any, spec: ConfigSpec, key: str, show: Callable[[Any], str] | None = None,
                 **kwargs: Any) -> None:
        kwargs.setdefault("default", None)
        super().__init__(*args, **kwargs)
        self.spec, self.key, self.show = spec, key, show

    def default_text(self) -> str:
        """The field's default as the option is written ("" for None)."""
        value = self.spec.default(self.key)
        if self.show is not None:
            return self.show(value)
        if value is None:
            return ""
        if isinstance(value, bool):
            return "on" if value else "off"
        if isinstance(value, (tuple, list)):
            return ",".join(str(v) for v in value)
        return f"{value:g}" if isinstance(value, float) else str(value)

    def get_help_record(self, ctx: click.Context) -> tuple[str, str] | None:
        if self.help is None:
            self.help = plain(self.spec.doc(self.key)).split("\n")[0]
        return super().get_help_record(ctx)

    def get_help_extra(self, ctx: click.Context) -> Any:
        extra = super().get_help_extra(ctx)
        text = self.default_text()
        if text:
            extra["default"] = text
        return extra


def field_option(*decls: str, spec: ConfigSpec, key: str, **kwargs: Any) -> Callable[[Callable[..., Any]], Callable[..., Any]]:
    """``click.option(*decls)`` filling ``key`` of ``spec`` (:class:`FieldOption`)."""
    return click.option(*decls, cls=FieldOption, spec=spec, key=key, **kwargs)
